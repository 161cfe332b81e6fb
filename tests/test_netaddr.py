"""The one loopback test (daq.netaddr.is_loopback) the shared bus, the Foxglove relay and the
web gateway ask before they warn about a wider bind."""
import pytest

from rsra.daq.netaddr import is_loopback


@pytest.mark.parametrize("host", ["127.0.0.1", "127.0.0.2", "localhost", "LocalHost", "::1",
                                  "[::1]", "::ffff:127.0.0.1", " 127.0.0.1 "])
def test_loopback_hosts(host):
    assert is_loopback(host)


@pytest.mark.parametrize("host", ["0.0.0.0", "::", "[::]", "", "192.168.1.2", "10.0.0.7",
                                  "[fe80::1]", "2001:db8::1", "example.org", "localhost.evil",
                                  "[127.0.0.1", "127.0.0.1]", "::ffff:192.168.1.2"])
def test_other_hosts(host):
    assert not is_loopback(host)


def test_the_three_servers_ask_the_same_function():
    from rsra.daq.runtime import foxglove_out
    from rsra.daq.web import server

    assert foxglove_out.is_loopback is is_loopback and server.is_loopback is is_loopback
    assert foxglove_out.risk_line("[::1]", 8765) is None
    assert "not loopback" in (foxglove_out.risk_line("0.0.0.0", 8765) or "")
