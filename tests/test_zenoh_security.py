"""Zenoh security and deployment (docs/deployment.md, docs/telemetry.md §1).

* The shipped example (config/zenoh/{router,rig,viewer}.json5, certificates from
  config/zenoh/make-certs.sh) works as docs/deployment.md says: a router (a Python session in
  router mode, as zenohd would run the same file) with mutual TLS, user/password and access
  control passes the rig's telemetry to an authorised viewer, refuses clients without the
  right certificate or password, drops viewers' publications and queryables, and drops the
  rig's publications outside `rsra/bench/**`.
* The service's default Zenoh config listens on loopback only and opens no multicast socket.
* No Zenoh message changes the service's state; it declares no subscriber.

Certificates and passwords are generated per run under tmp (never committed); loopback only,
free ports, multicast scouting off in every session opened here.
"""
from __future__ import annotations

import contextlib
import ipaddress
import json
import os
import secrets
import shutil
import socket
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import pytest
import zenoh

from rsra.config.rig import load_config
from rsra.daq.runtime.telemetry import STATE_KEYS, TelemetryPublisher, viewer_config, zenoh_config
from tests.helpers_net import free_tcp_port

ZENOH_DIR = Path(__file__).resolve().parents[1] / "config" / "zenoh"
MAKE_CERTS = ZENOH_DIR / "make-certs.sh"
TEMPLATE_DIR = "/etc/rsra/zenoh/"  # where the templates expect certificates and credentials
TEMPLATE_EP = "127.0.0.1:7447"  # the templates' router endpoint
RIG_PREFIX = "rsra/bench"
WAIT_S = 10.0  # upper bound on any propagation wait (a deadline, not a timing assertion)

def wait_until(pred: Callable[[], bool], timeout: float = WAIT_S) -> bool:
    """Poll a condition that Zenoh's asynchronous discovery makes true eventually."""
    deadline = time.monotonic() + timeout
    while not pred():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.01)
    return True


def matching(obj: zenoh.Publisher | zenoh.Querier) -> bool:
    """Whether a subscriber (queryable) matches this publisher (querier) anywhere in the
    network. (1.10 returns a MatchingStatus object, not the bool its stub declares.)"""
    return obj.matching_status.matching


def drain(handler) -> list[zenoh.Sample]:
    out = []
    while (s := handler.try_recv()) is not None:
        out.append(s)
    return out


# ---------------------------------------------------------------- the tested example


class Deployment:
    """Certificates, credentials and instantiated copies of the shipped templates."""

    def __init__(self, root: Path) -> None:
        self.root = root
        self.certs = root / "certs"
        self.port = free_tcp_port()
        self.passwords = {u: secrets.token_urlsafe(16) for u in (
            "rig-bench", "viewer-1", "viewer-2", "rsra-router", "rsra-router-2")}
        self._n = 0

    def make_certs(self) -> None:
        def run(*args: str) -> None:
            subprocess.run(["sh", str(MAKE_CERTS), *args], check=True, capture_output=True,
                           timeout=60)

        run(str(self.certs), "ca")
        for router in ("rsra-router", "rsra-router-2"):
            run(str(self.certs), "router", router, "localhost", "127.0.0.1")
        for name in ("rig-bench", "viewer-1", "viewer-2"):
            run(str(self.certs), "client", name)
        # the same client name, signed by a CA the router does not trust
        run(str(self.root / "rogue"), "ca")
        run(str(self.root / "rogue"), "client", "viewer-1")
        creds = self.certs / "credentials.txt"
        creds.write_text("".join(f"{u}:{p}\n" for u, p in self.passwords.items()))
        os.chmod(creds, 0o600)

    def instantiate(self, template: str, replace: dict[str, str] | None = None) -> str:
        """The template with only the deployment-specific strings changed: certificate
        directory, router port, the user's password (and whatever `replace` adds)."""
        text = (ZENOH_DIR / template).read_text()
        subs = {TEMPLATE_DIR: f"{self.certs}/", TEMPLATE_EP: f"127.0.0.1:{self.port}"}
        subs.update(replace or {})
        for old, new in subs.items():
            assert old in text, f"{template} has no {old!r}"
            text = text.replace(old, new)
        self._n += 1
        path = self.root / f"{self._n:02d}-{template}"
        path.write_text(text)
        os.chmod(path, 0o600)
        return str(path)

    def router_config(self, name: str = "rsra-router", port: int | None = None,
                      connect_to: int | None = None) -> zenoh.Config:
        """The router template as zenohd would load it; a second router of the mesh gets its
        own name (certificate, user), port and the first router as connect endpoint."""
        subs = {"CHANGE-ME": self.passwords[name]}
        if name != "rsra-router":
            subs.update({"/rsra-router.pem": f"/{name}.pem",
                         "/rsra-router-key.pem": f"/{name}-key.pem",
                         'user: "rsra-router"': f'user: "{name}"'})
        if port is not None:
            subs[f'listen: {{ endpoints: ["tls/127.0.0.1:{self.port}"] }}'] = \
                f'listen: {{ endpoints: ["tls/127.0.0.1:{port}"] }}'
        if connect_to is not None:
            subs["connect: { endpoints: [] }"] = \
                f'connect: {{ endpoints: ["tls/127.0.0.1:{connect_to}"] }}'
        return zenoh.Config.from_file(self.instantiate("router.json5", subs))

    def client(self, template: str, user: str, password: str | None = None,
               replace: dict[str, str] | None = None) -> zenoh.Config:
        """A rig or viewer config as the service / `rsra listen --zenoh-config` loads it."""
        subs = {"CHANGE-ME": self.passwords[user] if password is None else password}
        if template == "viewer.json5" and user != "viewer-1":
            subs["viewer-1"] = user
        subs.update(replace or {})
        return zenoh_config(load_config().telemetry, config_file=self.instantiate(template, subs))


@contextlib.contextmanager
def rig_service(deployment: Deployment, effective: dict | None = None):
    """The rig's session with the service's publisher, declared before any viewer joins (a
    client learns the queryables that exist when it opens)."""
    with zenoh.open(deployment.client("rig.json5", "rig-bench")) as rig:
        pub = TelemetryPublisher(rig, RIG_PREFIX, effective or {"rig": {"name": "bench"}})
        try:
            yield pub
        finally:
            pub.close()


@pytest.fixture(scope="module")
def deployment(tmp_path_factory):
    if shutil.which("openssl") is None or shutil.which("sh") is None:
        pytest.skip("make-certs.sh needs sh and the openssl command")
    d = Deployment(tmp_path_factory.mktemp("zenoh-deployment"))
    d.make_certs()
    with zenoh.open(d.router_config()) as router:
        d.router = router
        yield d


def test_deployment_doc_shows_the_tested_files_verbatim():
    doc = (ZENOH_DIR.parents[1] / "docs" / "deployment.md").read_text()
    for name in ("router.json5", "rig.json5", "viewer.json5"):
        assert f"```json5\n{(ZENOH_DIR / name).read_text()}```" in doc, name
    assert "rsra listen --prefix rsra/bench --zenoh-config /etc/rsra/zenoh/viewer.json5" in doc


def test_example_configs_are_loopback_tls_only_without_multicast(deployment):
    """What the service reads from the shipped files: TLS only, no listener on a client,
    multicast scouting off, ACL on with default deny."""
    rig = deployment.client("rig.json5", "rig-bench")
    assert json.loads(rig.get_json("mode")) == "client"
    assert json.loads(rig.get_json("listen/endpoints")) == []
    assert json.loads(rig.get_json("transport/link/protocols")) == ["tls"]
    assert json.loads(rig.get_json("transport/link/tls/enable_mtls")) is True
    assert json.loads(rig.get_json("scouting/multicast/enabled")) is False
    router = deployment.router_config()
    acl = json.loads(router.get_json("access_control"))
    assert acl["enabled"] is True and acl["default_permission"] == "deny"
    assert json.loads(router.get_json("listen/endpoints")) == [f"tls/127.0.0.1:{deployment.port}"]
    assert json.loads(router.get_json("scouting/multicast/enabled")) is False


def test_rig_publishes_through_router_to_authorised_viewer(deployment):
    cfg = load_config()
    effective = cfg.effective()
    effective["telemetry"]["zenoh_config"] = "/etc/rsra/zenoh/rig.json5"
    effective["zenoh"] = {"transport": {"auth": {"usrpwd": {"user": "rig-bench",
                                                            "password": "hunter2"}}}}
    with rig_service(deployment, effective) as pub, \
            zenoh.open(deployment.client("viewer.json5", "viewer-1")) as viewer:
        sub = viewer.declare_subscriber(f"{RIG_PREFIX}/**", zenoh.handlers.FifoChannel(1024))
        assert wait_until(lambda: matching(pub._pubs["angles"]))
        for seq in range(20):
            pub.publish("hub_loads", {"seq": seq, "H": [float(seq)] * 6})
        pub.publish("angles", {"seq": 19, "alpha": [0.01] * 14})
        got: dict[str, list[dict]] = {}

        def received() -> bool:
            for s in drain(sub.handler):
                got.setdefault(str(s.key_expr), []).append(json.loads(s.payload.to_string()))
            return f"{RIG_PREFIX}/angles" in got and f"{RIG_PREFIX}/hub_loads" in got

        assert wait_until(received)
        assert got[f"{RIG_PREFIX}/angles"] == [{"seq": 19, "alpha": [0.01] * 14}]
        seqs = [r["seq"] for r in got[f"{RIG_PREFIX}/hub_loads"]]
        assert seqs == sorted(seqs) and set(seqs) <= set(range(20))  # DROP may lose some
        assert all(r["H"] == [float(r["seq"])] * 6 for r in got[f"{RIG_PREFIX}/hub_loads"])
        # late joiners: state queries and the liveliness token pass the router too
        replies = {str(r.ok.key_expr): json.loads(r.ok.payload.to_string())
                   for r in viewer.get(f"{RIG_PREFIX}/state/*", timeout=5) if r.ok}
        assert set(replies) == {f"{RIG_PREFIX}/state/angles", f"{RIG_PREFIX}/state/config"}
        state_config = replies[f"{RIG_PREFIX}/state/config"]
        assert state_config["telemetry"]["zenoh_config"] == "<removed>"
        assert state_config["zenoh"]["transport"]["auth"]["usrpwd"] == {
            "user": "rig-bench", "password": "<removed>"}
        assert "hunter2" not in json.dumps(state_config)
        alive = [str(r.ok.key_expr) for r in viewer.liveliness().get(f"{RIG_PREFIX}/**",
                                                                      timeout=5) if r.ok]
        assert sorted(alive) == [f"{RIG_PREFIX}/alive", pub.instance.key]  # and who it is
        sub.undeclare()


def test_rsra_listen_with_viewer_config_through_router(deployment):
    """`rsra listen --prefix rsra/bench --json --zenoh-config viewer.json5`, as in the docs."""
    path = deployment.instantiate("viewer.json5", {"CHANGE-ME": deployment.passwords["viewer-1"]})
    with zenoh.open(deployment.client("rig.json5", "rig-bench")) as rig:
        pub = TelemetryPublisher(rig, RIG_PREFIX, {"rig": {"name": "bench"}})
        proc = subprocess.Popen(
            [sys.executable, "-m", "rsra", "listen", "--prefix", RIG_PREFIX, "--json",
             "--zenoh-config", path, "--count", "3", "--duration", "30"],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            # its subscription reaching the rig is the signal to publish (no sleeps)
            assert wait_until(lambda: matching(pub._pubs["angles"]) or proc.poll() is not None,
                              timeout=30)
            for seq in range(3):  # angles: congestion control BLOCK, nothing dropped
                pub.publish("angles", {"seq": seq, "accepted": True})
            out, err = proc.communicate(timeout=30)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.communicate()
            pub.close()
    assert proc.returncode == 0, err
    recs = [json.loads(line) for line in out.splitlines()]
    assert recs == [{"key": "angles", "seq": s, "accepted": True} for s in range(3)]


def test_rsra_run_with_rig_config_through_router(deployment):
    """`rsra run … --zenoh-config rig.json5`, as in the docs (with the simulator attached, one
    second of acquisition in lock-step): its telemetry reaches a viewer through the router."""
    path = deployment.instantiate("rig.json5", {"CHANGE-ME": deployment.passwords["rig-bench"]})
    with zenoh.open(deployment.client("viewer.json5", "viewer-1")) as viewer:
        sub = viewer.declare_subscriber(f"{RIG_PREFIX}/**", zenoh.handlers.FifoChannel(1 << 16))
        proc = subprocess.run(
            [sys.executable, "-m", "rsra", "run", "--sim", "ground-test", "--speed", "max",
             "--duration", "1", "--zenoh-config", path, "--log-level", "warning"],
            capture_output=True, text=True, timeout=120)
        assert proc.returncode == 0, proc.stderr[-2000:]
        got: dict[str, list[dict]] = {}
        for s in drain(sub.handler):
            got.setdefault(str(s.key_expr), []).append(json.loads(s.payload.to_string()))
        sub.undeclare()
    # (a record still in flight when drained is simply not counted)
    seqs = [r["seq"] for r in got.get(f"{RIG_PREFIX}/hub_loads", [])]
    assert seqs and seqs == sorted(seqs)  # DROP may lose a few at full speed, never reorder
    assert f"{RIG_PREFIX}/channels" in got


def _no_credentials(conf: zenoh.Config) -> None:
    conf.insert_json5("transport/auth/usrpwd", '{"user": null, "password": null}')


def _no_certificate(conf: zenoh.Config) -> None:
    conf.insert_json5("transport/link/tls/enable_mtls", "false")
    conf.insert_json5("transport/link/tls/connect_certificate", "null")
    conf.insert_json5("transport/link/tls/connect_private_key", "null")


REFUSED = {
    "wrong password": (dict(password="not-the-password"), None),
    "another user's password": (dict(password_of="viewer-2"), None),
    "no user/password": ({}, _no_credentials),
    "no client certificate": ({}, _no_certificate),
    "certificate from another CA": (dict(rogue=True), None),
    "rig certificate with viewer password": (dict(cert_of="rig-bench"), None),
}


@pytest.mark.parametrize("case", list(REFUSED))
def test_unauthenticated_client_is_refused_at_open(deployment, case):
    """Spec: refused connections fail at zenoh.open with a generic error. The unmodified
    viewer config opens (positive control); each single change makes open fail."""
    with zenoh.open(deployment.client("viewer.json5", "viewer-1")):
        pass
    opts, mutate = REFUSED[case]
    replace = {}
    if opts.get("rogue"):
        replace[f"{deployment.certs}/viewer-1"] = str(deployment.root / "rogue" / "viewer-1")
    if "cert_of" in opts:
        replace["/viewer-1.pem"] = f"/{opts['cert_of']}.pem"
        replace["/viewer-1-key.pem"] = f"/{opts['cert_of']}-key.pem"
    password = opts.get("password")
    if "password_of" in opts:
        password = deployment.passwords[opts["password_of"]]
    path = deployment.instantiate("viewer.json5", {
        "CHANGE-ME": deployment.passwords["viewer-1"] if password is None else password})
    if replace:  # second pass: paths only exist after the directory substitution
        text = Path(path).read_text()
        for old, new in replace.items():
            assert old in text
            text = text.replace(old, new)
        Path(path).write_text(text)
    conf = zenoh_config(load_config().telemetry, config_file=path)
    if mutate:
        mutate(conf)
    if case == "rig certificate with viewer password":
        # both credentials are valid on their own: the link opens, but the ACL subject needs
        # the CN and the user name together, so this client matches no subject (checked below)
        with zenoh.open(conf) as s:
            _assert_identity_mismatch_gets_nothing(deployment, s)
        return
    with pytest.raises(zenoh.ZError):
        zenoh.open(conf).close()


def _assert_identity_mismatch_gets_nothing(deployment: Deployment, mixed: zenoh.Session) -> None:
    with rig_service(deployment) as pub, \
            zenoh.open(deployment.client("viewer.json5", "viewer-2")) as ok:
        # control: a real viewer's subscription reaches the rig, its undeclaration too
        sub_ok = ok.declare_subscriber(f"{RIG_PREFIX}/angles")
        assert wait_until(lambda: matching(pub._pubs["angles"]))
        sub_ok.undeclare()
        assert wait_until(lambda: not matching(pub._pubs["angles"]))
        # the mixed client's subscription and query are dropped: no reply, although the
        # rig holds state/config
        sub = mixed.declare_subscriber(f"{RIG_PREFIX}/angles")
        assert [r for r in mixed.get(f"{RIG_PREFIX}/state/*", timeout=1) if r.ok] == []
        # barrier: had the router forwarded that declaration (control priority), the rig
        # would have it before this later query from the real viewer
        assert len([r for r in ok.get(f"{RIG_PREFIX}/state/config", timeout=5) if r.ok]) == 1
        assert not matching(pub._pubs["angles"])
        sub.undeclare()


def test_acl_drops_viewer_publications_and_rig_outside_prefix(deployment):
    """Viewers only subscribe and query; the rig publishes only under rsra/bench/**.

    Lock-step, no sleeps: messages on one link at one priority stay in order, so when a
    later allowed message has arrived, an earlier forbidden one would have arrived first."""
    with rig_service(deployment) as pub, \
            zenoh.open(deployment.client("viewer.json5", "viewer-1")) as v1, \
            zenoh.open(deployment.client("viewer.json5", "viewer-2")) as v2:
        rig = pub.session
        watch = v2.declare_subscriber("rsra/**", zenoh.handlers.FifoChannel(1024))
        marker = rig.declare_publisher(f"{RIG_PREFIX}/marker")
        outside = rig.declare_publisher("rsra/other/hub_loads")
        assert wait_until(lambda: matching(marker) and matching(outside))

        # 1. a viewer publishes (forged telemetry, a delete) and declares a queryable
        forged = v1.declare_queryable(f"{RIG_PREFIX}/state/forged")
        for key in (f"{RIG_PREFIX}/hub_loads", f"{RIG_PREFIX}/angles", "rsra/other/x"):
            v1.put(key, json.dumps({"seq": -1, "forged": True}))
        v1.delete(f"{RIG_PREFIX}/angles")
        # barrier: v1's query leaves after those (puts and queries share the data priority,
        # declarations go at control priority) and the router forwards in arrival order, so
        # once its reply is back anything forwarded to v2 is queued ahead of the marker below
        assert [str(r.ok.key_expr) for r in v1.get(f"{RIG_PREFIX}/state/config", timeout=5)
                if r.ok] == [f"{RIG_PREFIX}/state/config"]
        # 2. the rig publishes outside its prefix, then a marker inside it (same QoS)
        outside.put("outside")
        rig.put("rsra/bench2/hub_loads", "outside")
        rig.put("other/hub_loads", "outside")
        marker.put("end")
        seen: list[tuple[str, str]] = []

        def marker_seen() -> bool:
            seen.extend((str(s.key_expr), s.payload.to_string()) for s in drain(watch.handler))
            return (f"{RIG_PREFIX}/marker", "end") in seen

        assert wait_until(marker_seen)  # positive control: the path delivers
        assert seen == [(f"{RIG_PREFIX}/marker", "end")], seen

        # 3. the viewer's queryable is unreachable; the rig's state/* answers
        replies = [r.ok for r in v2.get(f"{RIG_PREFIX}/state/**", timeout=5) if r.ok]
        assert [str(r.key_expr) for r in replies] == [f"{RIG_PREFIX}/state/config"]
        assert forged.handler.try_recv() is None
        for obj in (watch, marker, outside, forged):
            obj.undeclare()


def test_two_router_mesh_carries_rig_to_remote_viewer_and_keeps_rules(deployment):
    """Many rigs and viewers: a second router (same template, its own certificate and user)
    connects to the first; the rig on router 1 reaches a viewer on router 2 — telemetry, state
    and liveliness — and router 2 still drops its viewer's publications."""
    port2 = free_tcp_port()
    viewer_on_2 = {f"127.0.0.1:{deployment.port}": f"127.0.0.1:{port2}"}
    with zenoh.open(deployment.router_config("rsra-router-2", port=port2,
                                             connect_to=deployment.port)), \
            rig_service(deployment) as pub, \
            zenoh.open(deployment.client("viewer.json5", "viewer-1", replace=viewer_on_2)) as v1, \
            zenoh.open(deployment.client("viewer.json5", "viewer-2")) as v2:
        rig = pub.session
        far = v1.declare_subscriber(f"{RIG_PREFIX}/**", zenoh.handlers.FifoChannel(1024))
        near = v2.declare_subscriber("rsra/**", zenoh.handlers.FifoChannel(1024))
        marker = rig.declare_publisher(f"{RIG_PREFIX}/marker")
        # both viewers' subscriptions have reached the rig once both see a marker
        got_far: list[str] = []
        got_near: list[tuple[str, str]] = []

        def both_seen() -> bool:
            marker.put("ping")
            got_far.extend(s.payload.to_string() for s in drain(far.handler))
            got_near.extend((str(s.key_expr), s.payload.to_string())
                            for s in drain(near.handler))
            return "ping" in got_far and (f"{RIG_PREFIX}/marker", "ping") in got_near

        assert wait_until(both_seen)
        pub.publish("angles", {"seq": 5, "accepted": True})
        replies = [json.loads(r.ok.payload.to_string())
                   for r in v1.get(f"{RIG_PREFIX}/state/angles", timeout=5) if r.ok]
        assert replies == [{"seq": 5, "accepted": True}]
        alive = [str(r.ok.key_expr) for r in v1.liveliness().get(f"{RIG_PREFIX}/alive",
                                                                  timeout=5) if r.ok]
        assert alive == [f"{RIG_PREFIX}/alive"]
        # the far viewer forges telemetry; its query (after, same priority) is the barrier
        drain(near.handler)
        got_near.clear()
        v1.put(f"{RIG_PREFIX}/hub_loads", "forged")
        v1.put("rsra/other/hub_loads", "forged")
        assert len([r for r in v1.get(f"{RIG_PREFIX}/state/config", timeout=5) if r.ok]) == 1
        marker.put("end")

        def end_seen() -> bool:
            got_near.extend((str(s.key_expr), s.payload.to_string())
                            for s in drain(near.handler))
            return (f"{RIG_PREFIX}/marker", "end") in got_near

        assert wait_until(end_seen)
        assert [(k, p) for k, p in got_near if p != "ping"] == [(f"{RIG_PREFIX}/marker", "end")]
        for obj in (far, near, marker):
            obj.undeclare()


# ---------------------------------------------------------------- the service's defaults


def _hex_addr(h: str) -> ipaddress.IPv4Address | ipaddress.IPv6Address:
    """/proc/net/{tcp,udp}[6] address: 32-bit words in host (little-endian) order."""
    raw = bytes.fromhex(h)
    raw = b"".join(raw[i:i + 4][::-1] for i in range(0, len(raw), 4))
    return ipaddress.ip_address(raw)


needs_procfs = pytest.mark.skipif(not Path("/proc/net/tcp").exists(),
                                  reason="socket inspection reads Linux /proc/net")


def own_sockets() -> dict[int, tuple[str, ipaddress.IPv4Address | ipaddress.IPv6Address, int, str]]:
    """This process's inet sockets: inode -> (proto, local address, port, state)."""
    inodes = set()
    for fd in os.listdir("/proc/self/fd"):
        try:
            link = os.readlink(f"/proc/self/fd/{fd}")
        except OSError:
            continue
        if link.startswith("socket:["):
            inodes.add(int(link[8:-1]))
    out = {}
    for proto in ("tcp", "tcp6", "udp", "udp6"):
        with open(f"/proc/net/{proto}") as f:
            next(f)
            for line in f:
                p = line.split()
                inode = int(p[9])
                if inode in inodes:
                    addr, port = p[1].split(":")
                    out[inode] = (proto, _hex_addr(addr), int(port, 16), p[3])
    return out


def exposure(new: dict) -> list[str]:
    """Why these sockets are not loopback-only TCP listeners (empty list: they are)."""
    bad = []
    for proto, addr, port, state in new.values():
        if proto.startswith("udp"):
            bad.append(f"{proto} socket on {addr}:{port}"
                       + (" (multicast)" if addr.is_multicast else ""))
        elif not addr.is_loopback:
            bad.append(f"{proto} socket on {addr}:{port} (state {state})")
    return bad


@needs_procfs
def test_socket_inspection_flags_exposed_sockets():
    """Positive control for the check below. Real sockets: a loopback listener is found and
    passes; a UDP socket bound to Zenoh's scouting group is found and flagged (bound only: no
    group joined, nothing sent). A listener on all interfaces is flagged too — synthetic, as
    this machine has a real interface to expose."""
    before = set(own_sockets())
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as t, \
            socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as u:
        t.bind(("127.0.0.1", 0))
        t.listen()
        u.bind(("224.0.0.224", 0))
        tport, uport = t.getsockname()[1], u.getsockname()[1]
        new = {k: v for k, v in own_sockets().items() if k not in before}
    assert sorted((proto, str(a), p, st) for proto, a, p, st in new.values()) == [
        ("tcp", "127.0.0.1", tport, "0A"), ("udp", "224.0.0.224", uport, "07")]
    assert exposure(new) == [f"udp socket on 224.0.0.224:{uport} (multicast)"]
    anywhere = {1: ("tcp", ipaddress.ip_address("0.0.0.0"), 7447, "0A"),
                2: ("tcp6", ipaddress.ip_address("::"), 7447, "0A")}
    assert len(exposure(anywhere)) == 2
    assert _hex_addr("0100007F") == ipaddress.ip_address("127.0.0.1")
    assert _hex_addr("00000000000000000000000001000000") == ipaddress.ip_address("::1")


@needs_procfs
def test_default_service_config_listens_on_loopback_only_without_multicast():
    cfg = load_config()
    # the effective config, as the service builds it from the default rig TOML
    conf = zenoh_config(cfg.telemetry)
    listen = json.loads(conf.get_json("listen/endpoints"))
    assert listen and all(ipaddress.ip_address(ep.split("/")[1].rsplit(":", 1)[0].strip("[]"))
                          .is_loopback for ep in listen), listen
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is False
    assert json.loads(conf.get_json("connect/endpoints")) == []
    # a live session with that config (only the port changed: never a fixed port in tests)
    port = free_tcp_port()
    live = [ep.rsplit(":", 1)[0] + f":{port}" for ep in listen]
    before = set(own_sockets())
    with zenoh.open(zenoh_config(cfg.telemetry, listen=live)):
        new = {k: v for k, v in own_sockets().items() if k not in before}
    assert exposure(new) == []
    listeners = {(str(a), p) for proto, a, p, st in new.values() if st == "0A"}  # TCP_LISTEN
    assert listeners == {(ep.split("/")[1].rsplit(":", 1)[0].strip("[]"), port) for ep in live}


@needs_procfs
def test_zenoh_file_without_listen_or_scouting_gets_safe_defaults(tmp_path):
    """A --zenoh-config file that omits them must not fall back to Zenoh's defaults
    (multicast scouting on, a peer listening on every interface)."""
    path = tmp_path / "minimal.json5"
    path.write_text('{ mode: "peer", connect: { endpoints: [] } }')
    conf = zenoh_config(load_config().telemetry, config_file=str(path))
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is False
    assert json.loads(conf.get_json("listen/endpoints")) == []
    before = set(own_sockets())
    with zenoh.open(conf):
        new = {k: v for k, v in own_sockets().items() if k not in before}
    assert exposure(new) == [] and new == {}


def test_no_zenoh_message_changes_service_state():
    """Telemetry is read-only: puts, deletes and queries (with payloads) on every key under
    the prefix, state/* included, leave the cached state, the counters and the published
    records unchanged; the service declares no subscriber and no queryable but state/*."""
    cfg = load_config()
    prefix = "rsra/bench"
    ep = f"tcp/127.0.0.1:{free_tcp_port()}"
    with zenoh.open(zenoh_config(cfg.telemetry, listen=[ep])) as service, \
            zenoh.open(viewer_config([ep])) as attacker:
        pub = TelemetryPublisher(service, prefix, cfg.effective())
        try:
            pub.publish("angles", {"seq": 1, "alpha": [0.02] * 14, "accepted": True})
            pub.publish("health", {"t": 1.0, "nodes": {}})
            pub.publish("hub_loads", {"seq": 1, "H": [1.0] * 6})
            state0 = dict(pub._state)
            published0, errors0 = dict(pub.published), pub.errors
            keys = ([f"{prefix}/{k}" for k in ("hub_loads", "channels", "angles", "innovations",
                                               "health", "alive", "config", "command", "a/b/c")]
                    + [f"{prefix}/state/{k}" for k in (*STATE_KEYS, "forged", "x/y")]
                    + ["rsra/other/state/config", "other"])
            forged = json.dumps({"seq": 999, "alpha": [9.0] * 14, "accepted": True,
                                 "telemetry": {"prefix": "hijacked"}})
            for key in keys:
                attacker.put(key, forged)
                attacker.delete(key)
            for sel in (f"{prefix}/**", f"{prefix}/state/*", f"{prefix}/state/config", "**",
                        f"{prefix}/state/config?set=1", f"{prefix}/hub_loads"):
                for r in attacker.get(sel, payload=forged, timeout=5):
                    if r.ok:  # only the cached records, byte for byte
                        name = str(r.ok.key_expr).rsplit("/", 1)[-1]
                        assert str(r.ok.key_expr) == f"{prefix}/state/{name}"
                        assert r.ok.payload.to_bytes() == state0[name]
            assert pub._state == state0
            assert pub.published == published0 and pub.errors == errors0

            # no subscriber anywhere in the service: nothing matches the attacker's keys…
            pubs = [attacker.declare_publisher(k) for k in keys]
            assert not any(matching(p) for p in pubs)
            # …and no queryable but state/*
            q_state = attacker.declare_querier(f"{prefix}/state/config")
            q_other = [attacker.declare_querier(f"{prefix}/{k}")
                       for k in ("hub_loads", "angles", "config", "command", "a/**")]
            assert wait_until(lambda: matching(q_state))
            assert not any(matching(q) for q in q_other)
            # positive control: a subscriber declared in the service's session is seen
            watch = service.declare_subscriber(f"{prefix}/angles")
            assert wait_until(lambda: matching(pubs[keys.index(f"{prefix}/angles")]))
            watch.undeclare()
            for obj in (*pubs, q_state, *q_other):
                obj.undeclare()
        finally:
            pub.close()
