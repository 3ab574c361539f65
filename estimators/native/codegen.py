"""CasADi functions compiled to C once, cached by content hash, and called through ctypes.

Why not just call the CasADi `Function` from Python: a Python-level call converts every argument (numpy
-> DM -> numpy) before any arithmetic, which costs more than a small model's arithmetic, and the MHE makes a
few calls per time step; the SX virtual machine also runs several times slower than the same code compiled.
Here a `Function` is turned into C with CasADi's own code generator, compiled with the system C
compiler (`cc -O1 -shared`), kept in a cache directory under the hash of its source, and called with
pointers to preallocated numpy buffers: a call costs little beyond the arithmetic.

What is compiled is the model's structure, not its numbers: the estimators pass a model's weights,
physical parameters and dt (and the MHE's Q⁻¹, R⁻¹) as an input filled once (`estimators.parametric`),
so every trained model of one architecture hits the library the first one built.

`compiled(...)` returns one callable per function with the same interface whatever happened: when no
compiler is found or compiling fails, the callable wraps the CasADi `Function` itself (slower, same
numbers) and says so in its `backend` attribute.  Only dense inputs and outputs are supported; the
buffers are column-major like CasADi, so a (rows, cols) CasADi matrix is a numpy (cols, rows) array.
"""
from __future__ import annotations

import ctypes
import hashlib
import os
import shutil
import subprocess
import tempfile
import warnings
from pathlib import Path

import casadi as ca
import numpy as np

DEFAULT_CACHE = Path.home() / ".cache" / "learnest" / "codegen"
# -O1: CasADi's long straight-line functions (a KNODE's exact Jacobian runs to tens of thousands of
# instructions) compile in a fraction of -O2's time, and the estimators run as fast with either within the
# timing noise, so -O2 would only make every new architecture wait longer before its first use.
# btd.c/gn.c, small and hand-written, use -O2 (mhe_gn.BlockTridiagonal)
CFLAGS = ("-O1", "-fPIC", "-shared")


def find_compiler() -> str | None:
    """The system C compiler, or None (then everything runs in CasADi's virtual machine)."""
    for name in ("cc", "gcc", "clang"):
        path = shutil.which(name)
        if path:
            return path
    return None


class _Buffers:
    """Dense input and output arrays of one function, shaped (cols, rows) = CasADi's column-major."""

    def __init__(self, fn: ca.Function):
        for i in range(fn.n_out()):
            if not fn.sparsity_out(i).is_dense():
                raise ValueError(f"{fn.name()}: output {i} is sparse; densify it before compiling")
        for i in range(fn.n_in()):
            if not fn.sparsity_in(i).is_dense():
                raise ValueError(f"{fn.name()}: input {i} is sparse")
        self.inputs = [np.zeros((fn.size2_in(i), fn.size1_in(i))) for i in range(fn.n_in())]
        self.outputs = [np.zeros((fn.size2_out(i), fn.size1_out(i))) for i in range(fn.n_out())]


class CompiledFunction(_Buffers):
    """Call a compiled CasADi function: fill `inputs[i][...]`, call, read `outputs[i]` (no copies)."""

    backend = "c"

    def __init__(self, fn: ca.Function, lib: ctypes.CDLL):
        super().__init__(fn)
        name = fn.name()
        work = getattr(lib, f"{name}_work")
        sizes = [ctypes.c_longlong() for _ in range(4)]
        if work(*(ctypes.byref(s) for s in sizes)):
            raise RuntimeError(f"{name}_work failed")
        sz_arg, sz_res, sz_iw, sz_w = (max(s.value, 1) for s in sizes)
        getattr(lib, f"{name}_incref")()
        self._mem = getattr(lib, f"{name}_checkout")()
        self._iw = np.zeros(sz_iw, dtype=np.int64)
        self._w = np.zeros(sz_w)
        self._arg = (ctypes.c_void_p * sz_arg)(*[a.ctypes.data for a in self.inputs])
        self._res = (ctypes.c_void_p * sz_res)(*[r.ctypes.data for r in self.outputs])
        self._fn = getattr(lib, name)
        self._fn.restype = ctypes.c_int
        self._fn.argtypes = [ctypes.c_void_p] * 4 + [ctypes.c_int]
        self._call_args = (ctypes.addressof(self._arg), ctypes.addressof(self._res),
                           self._iw.ctypes.data, self._w.ctypes.data, self._mem)
        self._lib = lib  # keep the library loaded as long as the callable lives

    def pointers(self) -> tuple:
        """(function, arg, res, iw, w, mem) as integers: what C code needs to call this function itself
        (`estimators/native/gn.c`), valid as long as this object lives."""
        return (ctypes.cast(self._fn, ctypes.c_void_p).value, *self._call_args)

    def __call__(self):
        if self._fn(*self._call_args):
            raise RuntimeError("compiled CasADi function returned an error")
        return self.outputs


class InterpretedFunction(_Buffers):
    """The same interface over CasADi's own evaluator (no compiler, or compiling failed)."""

    backend = "casadi"

    def __init__(self, fn: ca.Function):
        super().__init__(fn)
        self._fn = fn

    def __call__(self):
        results = self._fn.call([ca.DM(a.T) for a in self.inputs])
        for out, value in zip(self.outputs, results):
            out[...] = np.asarray(value).T
        return self.outputs


def mapped(fn: ca.Function, name: str, count: int, shared: tuple[int, ...] = ()) -> ca.Function:
    """``fn`` evaluated on ``count`` columns of its inputs, except the ``shared`` inputs, which every
    evaluation gets whole (a model's parameters): input i is (rows, count · cols), or as in ``fn`` when
    shared; outputs side by side, (rows, count · cols).

    Why not ``fn.map(name, "serial", count, shared, [])``: CasADi's map copies each shared input
    ``count`` times into its work array on every call (repmat), ~6,600 doubles per MHE gradient sweep for
    a 16-unit KNODE; here one function calls ``fn`` ``count`` times with the same pointer.
    """
    inputs = [ca.MX.sym(f"i{i}", fn.size1_in(i), fn.size2_in(i) * (1 if i in shared else count))
              for i in range(fn.n_in())]
    columns: list[list] = [[] for _ in range(fn.n_out())]
    for k in range(count):
        args = [inputs[i] if i in shared else inputs[i][:, k * fn.size2_in(i):(k + 1) * fn.size2_in(i)]
                for i in range(fn.n_in())]
        for j, out in enumerate(fn.call(args)):
            columns[j].append(out)
    return ca.Function(name, inputs, [ca.horzcat(*outs) for outs in columns])


# libraries loaded in this process, by `compiled`'s key: generating the C code only to hash it for the
# file cache is slow (CodeGenerator.add), and would be paid again for every flight
_LOADED: dict[str, ctypes.CDLL] = {}


def compiled(functions: list[ca.Function], cache_dir: str | Path | None = None,
             compiler: str | None = "auto", key: str | None = None) -> list:
    """One callable per CasADi function, compiled together into one shared library and cached.

    Parameters
    ----------
    functions : list of casadi.Function
        Dense inputs and outputs only.
    cache_dir : path, optional
        Where compiled libraries are kept (default ``~/.cache/learnest/codegen``); the file name is the
        sha256 of the generated source and the compiler flags, so a library is built once per content.
    compiler : str or None
        "auto" finds cc/gcc/clang; None forces CasADi's interpreter.
    key : str, optional
        An exact description of what ``functions`` compute that is cheaper to get than their C code: the
        serialized CasADi function they were all derived from plus every parameter of that derivation
        (`model_key`).  A library loaded in this process under the same key (and the same names, cache
        directory and compiler) is reused without generating code.  Two different sets of functions must
        never share a key: when in doubt, pass none.

    Returns
    -------
    list of CompiledFunction or InterpretedFunction, in the order given.
    """
    memo = None
    if key is not None:
        names = ",".join(fn.name() for fn in functions)
        cache = Path(cache_dir) if cache_dir is not None else DEFAULT_CACHE   # as load_source resolves it
        memo = hashlib.sha256("\0".join([key, names, str(cache), str(compiler), *CFLAGS]).encode()).hexdigest()
    lib = _LOADED.get(memo) if memo is not None else None
    if lib is None:
        generator = ca.CodeGenerator("learnest_fn.c", {"with_header": False})
        for fn in functions:
            generator.add(fn)
        lib = load_source(generator.dump(), cache_dir, compiler)
        if lib is None:
            return [InterpretedFunction(f) for f in functions]
        if memo is not None:
            _LOADED[memo] = lib
    return [CompiledFunction(f, lib) for f in functions]


def model_key(model: ca.Function, *derivation) -> str:
    """`compiled`'s key for functions derived from ``model`` (its inputs and outputs the symbols they were
    built from) by code whose every other choice is in ``derivation`` (sizes, flags): serializing the model is
    far cheaper than generating the code it keys.  CasADi's serialization is exact (every
    instruction and constant) and deterministic for the same graph."""
    return "\0".join([model.serialize(), *map(repr, derivation)])


def load_source(source: str, cache_dir: str | Path | None = None, compiler: str | None = "auto",
                flags: tuple = CFLAGS):
    """The shared library built from C `source` (cached by its hash), or None without a working compiler."""
    compiler = find_compiler() if compiler == "auto" else compiler
    if compiler is None:
        return None
    digest = hashlib.sha256("\0".join([source, compiler, *flags]).encode()).hexdigest()[:32]
    cache = Path(cache_dir) if cache_dir is not None else DEFAULT_CACHE
    library = cache / f"{digest}.so"
    try:
        if not library.exists():
            _compile(source, library, compiler, flags)
        return ctypes.CDLL(str(library))
    except (OSError, RuntimeError, subprocess.SubprocessError) as err:
        warnings.warn(f"compiling C code failed ({err}); using CasADi's interpreter and numpy", RuntimeWarning,
                      stacklevel=3)
        return None


def _compile(source: str, library: Path, compiler: str, flags: tuple) -> None:
    """Compile into a temporary file and rename: a concurrent reader never loads half a library."""
    library.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=library.parent) as tmp:
        c_file = Path(tmp) / "learnest_fn.c"
        c_file.write_text(source)
        out = Path(tmp) / library.name
        result = subprocess.run([compiler, *flags, str(c_file), "-o", str(out), "-lm"],
                                capture_output=True, text=True, timeout=600)
        if result.returncode:
            raise RuntimeError(f"{compiler} failed: {result.stderr[-2000:]}")
        os.replace(out, library)
