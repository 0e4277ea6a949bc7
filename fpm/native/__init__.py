"""The runtime's step compiled: the C step of ``fpm_step.c`` (built on first use with the
system's C compiler and loaded with ctypes), or a numba step where there is no compiler.

:class:`fpm.runtime.Runtime` picks its backend with :func:`engine`: ``"native"`` (the C step),
``"numba"``, ``"numpy"`` (the recipe itself, no engine) or ``"auto"`` (the first of these that
works; the default, or the environment variable ``FPM_RUNTIME_BACKEND``). Environment:

- ``FPM_CC``: the C compiler (default ``cc``; ``none`` for none, as on a machine without one);
- ``FPM_NATIVE_CACHE``: where the compiled library is kept (default
  ``$XDG_CACHE_HOME/fpm-native`` or ``~/.cache/fpm-native``), one file per source, compiler,
  flags and precision, so it compiles once per machine.

The library is compiled with ``-O3 -march=native -ffp-contract=off`` (no fused multiply-add:
the float64 step is then the NumPy recipe's arithmetic, summed in another order),
``-fno-math-errno -fno-trapping-math`` (so that square roots vectorise and a block's lanes past
its end may be computed and dropped: the values are the same) and ``-fopenmp`` when the compiler
has it.
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import platform
import shutil
import subprocess
import tempfile
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

if TYPE_CHECKING:
    from ..runtime import Runtime

HERE = Path(__file__).resolve().parent
SOURCE, HEADER = HERE / "fpm_step.c", HERE / "fpm_step.h"
BACKENDS = ("auto", "native", "numba", "numpy")
FLAGS = [
    "-std=c99", "-O3", "-march=native", "-ffp-contract=off", "-fno-math-errno",
    "-fno-trapping-math", "-fPIC", "-shared",
]  # fmt: skip
"""Compiler flags; ``-fopenmp`` is tried first, then without it (one thread)."""
PRECISIONS = {"float64": np.float64, "float32": np.float32}


class CompilerUnavailable(RuntimeError):
    """No C compiler, or it failed on the step's source."""


class NativeError(ValueError):
    """The C step refused the model or a step (the message names the field)."""


class Engine(Protocol):
    """A compiled step over a :class:`~fpm.runtime.Runtime`'s arrays."""

    name: str
    dtype: Any

    def step(
        self, x: np.ndarray, x_next: np.ndarray, v: np.ndarray, forces: np.ndarray | None
    ) -> tuple[float, bool]: ...

    def internal_forces(self, x: np.ndarray) -> np.ndarray: ...

    def reset(self) -> None: ...


def cache_dir() -> Path:
    """Where the compiled library is kept."""
    if os.environ.get("FPM_NATIVE_CACHE"):
        return Path(os.environ["FPM_NATIVE_CACHE"])
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "fpm-native"


def compiler() -> str | None:
    """The C compiler's path (``FPM_CC``, else ``cc``), or None."""
    name = os.environ.get("FPM_CC", "cc")
    return None if name.lower() in ("", "none") else shutil.which(name)


_libraries: dict[tuple[str, str], ctypes.CDLL] = {}


def library(precision: str = "float64") -> ctypes.CDLL:
    """The compiled step (compiled now if it is not in the cache).

    Raises:
        CompilerUnavailable: no compiler, or it failed (its message included).
    """
    cc = compiler()
    if cc is None:
        raise CompilerUnavailable(f"no C compiler (FPM_CC={os.environ.get('FPM_CC', 'cc')!r})")
    if (cc, precision) in _libraries:
        return _libraries[(cc, precision)]
    extra = ["-DFPM_FLOAT32"] if precision == "float32" else []
    errors = []
    for flags in (FLAGS + ["-fopenmp"] + extra, FLAGS + extra):
        digest = hashlib.sha256(
            SOURCE.read_bytes()
            + HEADER.read_bytes()
            + " ".join([cc, *flags]).encode()
            + platform.machine().encode()
            + platform.node().encode()
        ).hexdigest()[:16]
        target = cache_dir() / f"fpm_step-{precision}-{digest}{_suffix()}"
        if not target.exists():
            target.parent.mkdir(parents=True, exist_ok=True)
            with tempfile.TemporaryDirectory(dir=target.parent) as tmp:
                built = Path(tmp) / target.name
                run = subprocess.run(
                    [cc, *flags, str(SOURCE), "-o", str(built), "-lm"],
                    capture_output=True,
                    text=True,
                )
                if run.returncode != 0:
                    errors.append(run.stderr.strip().splitlines()[-1:] or ["failed"])
                    continue
                os.replace(built, target)  # atomic: another process may compile the same
        lib = ctypes.CDLL(str(target))
        _declare(lib)
        _libraries[(cc, precision)] = lib
        return lib
    raise CompilerUnavailable(f"{cc} could not compile {SOURCE.name}: {errors[-1][0]}")


def _suffix() -> str:
    return {"Darwin": ".dylib", "Windows": ".dll"}.get(platform.system(), ".so")


def _declare(lib: ctypes.CDLL) -> None:
    p, u32, dbl, i = ctypes.c_void_p, ctypes.c_uint32, ctypes.c_double, ctypes.c_int
    signatures: dict[str, tuple[Any, list[Any]]] = {
        "fpm_load": (i, [p, ctypes.c_size_t, ctypes.POINTER(p), ctypes.c_char_p, ctypes.c_size_t]),
        "fpm_free": (None, [p]),
        "fpm_error": (ctypes.c_char_p, [p]),
        "fpm_node_count": (u32, [p]),
        "fpm_dt": (dbl, [p]),
        "fpm_damping": (dbl, [p]),
        "fpm_stable_dt": (dbl, [p]),
        "fpm_set_parameters": (i, [p, dbl, dbl]),
        "fpm_set_threads": (i, [p, i]),
        "fpm_thread_count": (i, [p]),
        "fpm_internal_forces": (i, [p, p, p]),
        "fpm_reset": (None, [p]),
        "fpm_step": (i, [p, p, p, p, p, p]),
    }
    for name, (restype, argtypes) in signatures.items():
        fn = getattr(lib, name)
        fn.restype, fn.argtypes = restype, argtypes


class _Stats(ctypes.Structure):
    _fields_ = [
        ("unbalanced", ctypes.c_double),
        ("load", ctypes.c_double),
        ("settled", ctypes.c_int),
    ]


class NativeStep:
    """The C step of a binary export (:mod:`fpm.io.export_binary`'s bytes)."""

    name = "native"

    def __init__(self, data: bytes, precision: str = "float64", threads: int = 0) -> None:
        self.dtype = PRECISIONS[precision]
        self._lib = library(precision)
        handle = ctypes.c_void_p()
        error = ctypes.create_string_buffer(512)
        status = self._lib.fpm_load(data, len(data), ctypes.byref(handle), error, len(error))
        if status != 0:
            raise NativeError(error.value.decode())
        self._model = handle
        self.n_nodes = int(self._lib.fpm_node_count(handle))
        self._stats = _Stats()
        self._stats_ref = ctypes.byref(self._stats)
        self._states: dict[int, tuple[np.ndarray, int]] = {}
        self.threads = threads

    def __del__(self) -> None:
        model = getattr(self, "_model", None)
        if model:
            self._lib.fpm_free(model)

    @property
    def threads(self) -> int:
        return self._threads

    @threads.setter
    def threads(self, threads: int) -> None:
        self._check(self._lib.fpm_set_threads(self._model, int(threads)))
        self._threads = int(threads)

    @property
    def thread_count(self) -> int:
        """The threads the step runs on."""
        return int(self._lib.fpm_thread_count(self._model))

    @property
    def stable_dt(self) -> float:
        """Gershgorin's guaranteed-stable dt near rest, s."""
        return float(self._lib.fpm_stable_dt(self._model))

    def set_parameters(self, d: float, dt: float) -> None:
        self._check(self._lib.fpm_set_parameters(self._model, float(d), float(dt)))

    def _check(self, status: int) -> None:
        if status != 0:
            raise NativeError(self._lib.fpm_error(self._model).decode())

    def _array(self, a: np.ndarray, name: str) -> int:
        if a.dtype != self.dtype or not a.flags.c_contiguous or a.size != 3 * self.n_nodes:
            raise ValueError(
                f"{name}: need a C-contiguous {np.dtype(self.dtype).name} array of "
                f"{3 * self.n_nodes} values"
            )
        return a.ctypes.data

    def _state(self, a: np.ndarray, name: str) -> int:
        """The address of a state array (x, x_next, v), checked once: a runtime steps the same
        three arrays again and again, and the check costs microseconds a step. The array is
        held while its address is kept, so that its id stays its own."""
        kept = self._states.get(id(a))
        if kept is not None and kept[0] is a:
            return kept[1]
        if len(self._states) >= 6:
            self._states.clear()
        address = self._array(a, name)
        self._states[id(a)] = (a, address)
        return address

    def step(
        self, x: np.ndarray, x_next: np.ndarray, v: np.ndarray, forces: np.ndarray | None
    ) -> tuple[float, bool]:
        """One step: x_next from x, v in place; (the largest unbalanced force, settled)."""
        f = None if forces is None else self._array(forces, "forces")
        self._check(
            self._lib.fpm_step(
                self._model,
                self._state(x, "x"),
                self._state(x_next, "x_next"),
                self._state(v, "v"),
                f,
                self._stats_ref,
            )
        )
        return self._stats.unbalanced, bool(self._stats.settled)

    def internal_forces(self, x: np.ndarray) -> np.ndarray:
        x = np.ascontiguousarray(x, dtype=self.dtype)
        out = np.empty_like(x)
        self._check(
            self._lib.fpm_internal_forces(self._model, self._array(x, "x"), out.ctypes.data)
        )
        return out

    def reset(self) -> None:
        self._lib.fpm_reset(self._model)


def runtime_bytes(rt: Runtime) -> bytes:
    """A runtime's model in the binary layout (no load cases: its steps take the forces)."""
    from ..io.export_binary import pack

    shares = None
    if rt.shares is not None:
        s = rt.shares.tocsr()
        rows = np.flatnonzero(np.diff(s.indptr))
        counts = np.diff(s.indptr)[rows]
        shares = (rows, np.concatenate([[0], np.cumsum(counts)]), s.indices, s.data)
    return pack(
        nodes=rt.rest,
        masses=rt.masses,
        fixed=np.flatnonzero(rt.fixed),
        springs=rt.springs,
        rest_lengths=rt.rest_lengths,
        stiffness=rt.stiffness,
        hexahedra=rt.hexahedra,
        volume_stiffness=rt.kappa,
        rest_volumes=rt.rest_volumes,
        d=rt.d,
        dt=rt.dt,
        settle_tolerance=rt.settle_tolerance,
        settle_stiffness=rt.settle_stiffness,
        gravity=[float(g) for g in rt.gravity],
        shares=shares,
    )


def engine(rt: Runtime, backend: str = "auto", precision: str = "float64") -> Engine | None:
    """The compiled step for ``rt`` by ``backend`` (:data:`BACKENDS`; None: the NumPy recipe).
    ``"auto"``: the C step, else (no compiler) numba, else NumPy; float32 is the C step's."""
    if backend not in BACKENDS:
        raise ValueError(f"backend: {backend!r}, one of {', '.join(BACKENDS)}")
    if precision not in PRECISIONS:
        raise ValueError(f"precision: {precision!r}, one of {', '.join(PRECISIONS)}")
    if backend == "numpy":
        if precision != "float64":
            raise ValueError("precision: the NumPy recipe is float64")
        return None
    if backend in ("auto", "native"):
        try:
            return NativeStep(runtime_bytes(rt), precision)
        except CompilerUnavailable:
            if backend == "native" or precision != "float64":
                raise
    if precision != "float64":
        raise ValueError("precision: float32 is the C step's (backend native)")
    try:
        from .numba_step import NumbaStep
    except ImportError:
        if backend == "numba":
            raise
        return None
    return NumbaStep(rt)
