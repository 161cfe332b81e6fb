# The compiled hub path's interface (daq/_hubkernel.c, built by setup.py) for the type
# checker: a C extension publishes no annotations of its own. Buffers are float64 (or, for
# unpack_cal's codes and perm, bytes and Py_ssize_t) arrays passed by the buffer protocol.
from typing import Any

from typing_extensions import Buffer

class Plan:
    """The matrices and state arrays of one design and angles (held, not copied)."""

    def __init__(
        self, Mf: Any, Rinv: Any, S: Any, G: Any, buf: Any, Mb: Any, v: Any, Q2: Any,
        D: Any, bound2: Any, n: int, one_minus_beta: float, threshold: float,
        frame_json: str, *, fs_Rinv: Any = ..., fs_Bu: Any = ..., fs_modelled: Any = ...,
        fs_g2: Any = ..., fs_Mf: Any = ..., fs_Ms: Any = ..., fs_floor: Any = ...,
        beta_fast: float = ..., beta_slow: float = ...,
    ) -> None: ...
    def step(
        self, T: Buffer, accel: Buffer, q: Buffer | None, out: Buffer, seq: int, sync: int,
        t: float, omega: Any, flags: list[str], tail: tuple[str, ...], encode: bool = ...,
        fs: int = ..., /,
    ) -> tuple[bytes | None, float, float, bool, bool]: ...

def set_blas(dgemv_address: int, ddot_address: int, ilp64: bool, /) -> None: ...
def sos_step(sos: Buffer, zi: Buffer, x: Buffer, y: Buffer, /) -> None: ...
def unpack_cal(
    data: Buffer, codes: Buffer, perm: Buffer, gain: Buffer, offset: Buffer, out: Buffer,
    status_idx: tuple[int, ...], /,
) -> tuple[int, ...] | None: ...
def gemv(A: Buffer, m: int, k: int, fortran: bool, x: Buffer, y: Buffer, /) -> None: ...
