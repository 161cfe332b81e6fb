"""The one part of the build pyproject.toml cannot declare: the compiled hub path
(daq/_hubkernel.c → rsra.daq._hubkernel; docs/performance.md "The compiled hub path").

A plain C extension (the Python C API and the buffer protocol, no numpy headers): built by
the C compiler setuptools finds, with nothing to install first. ``optional``: where no
compiler is found the package still installs and the service runs the pure-Python path
(and says so in its log and in ``health``).
"""
from setuptools import Extension, setup

setup(ext_modules=[Extension(
    "rsra.daq._hubkernel", ["daq/_hubkernel.c"],
    # the same IEEE operations as numpy's, in the same order: no fused multiply-add
    extra_compile_args=["-O2", "-ffp-contract=off", "-fno-fast-math"],
    optional=True)])
