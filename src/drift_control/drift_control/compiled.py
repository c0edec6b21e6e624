"""Compiled casadi Functions: C from casadi, built by gcc into a cache, called through ctypes.

``build_cached`` writes a Function's C, compiles it into ``<cache>/<name>_<hash>.so`` (the hash of
the C source, flags and casadi version: a changed problem never gets stale code) and returns the
path, or None without gcc. ``CompiledFunction`` calls such a library on numpy buffers allocated
once: a call from Python costs a few microseconds, where a casadi ``Function`` call converts
every argument and result (~50 us on the 2-core machine, more than many of our functions take).
"""
from __future__ import annotations

import ctypes
import hashlib
import logging
import os
import re
import shutil
import subprocess
import tempfile
import time
from pathlib import Path

import casadi as ca
import numpy as np

log = logging.getLogger(__name__)

# HPIPM and BLASFEO ship with casadi: headers in include/, libraries next to the module
CASADI_DIR = Path(ca.__file__).resolve().parent
HPIPM_FLAGS = (f'-I{CASADI_DIR / "include"}', f'-L{CASADI_DIR}', f'-Wl,-rpath,{CASADI_DIR}',
               '-lhpipm', '-lblasfeo')


def build_cached(fn, name: str, cache: Path, gcc_flags=('-O2',), link=(),
                 dependencies: bool = False) -> Path | None:
    """Generate C for ``fn`` (a Function, or an nlpsol's dependencies), compile, return the .so.

    Returns None when gcc is missing or the compilation fails (the caller stays interpreted).
    ``link``: extra compiler and linker arguments (``HPIPM_FLAGS`` for a Function with HPIPM,
    whose generated options are completed by ``hpipm_defaults``).
    """
    if shutil.which('gcc') is None:
        log.warning('gcc not found: %s runs interpreted', name)
        return None
    try:
        return _build_cached(fn, name, Path(cache), tuple(gcc_flags), tuple(link), dependencies)
    except OSError as err:   # e.g. a read-only install: slower, not broken
        log.warning('cannot compile %s (%s): running interpreted', name, err)
        return None


def _build_cached(fn, name, cache: Path, gcc_flags, link, dependencies) -> Path | None:
    cache.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=cache) as tmp:
        c_file = f'{name}.c'
        cwd = os.getcwd()
        try:   # casadi writes into the working directory
            os.chdir(tmp)
            if dependencies:
                fn.generate_dependencies(c_file)
            else:
                fn.generate(c_file)
        finally:
            os.chdir(cwd)
        source = hpipm_defaults((Path(tmp) / c_file).read_text()).encode()
        (Path(tmp) / c_file).write_bytes(source)
        key = hashlib.sha256(source + ' '.join(gcc_flags + link).encode()
                             + ca.__version__.encode()).hexdigest()[:16]
        so = cache / f'{name}_{key}.so'
        if so.exists():
            return so
        t0 = time.perf_counter()
        tmp_so = Path(tmp) / so.name
        cmd = ['gcc', '-shared', '-fPIC', *gcc_flags, '-o', str(tmp_so), str(Path(tmp) / c_file),
               *link, '-lm']
        done = subprocess.run(cmd, capture_output=True, text=True)
        if done.returncode != 0:
            log.warning('gcc failed for %s, running interpreted: %s', name, done.stderr[-500:])
            return None
        os.replace(tmp_so, so)   # atomic: a concurrent process sees all or nothing
        log.info('compiled %s in %.1f s -> %s', name, time.perf_counter() - t0, so)
        return so


def hpipm_defaults(source: str) -> str:
    """HPIPM's defaults for the solver options casadi's C leaves unset.

    casadi 3.8 writes the options of its HPIPM interface field by field into an uninitialised
    ``d_ocp_qp_ipm_arg``; the fields this HPIPM has beyond those (``dual_gap_max``, ``t0_init``,
    ...) hold whatever was on the stack, and the QP then never met its exit condition. They get
    the values of ``d_ocp_qp_ipm_arg_set_default`` for the mode, as in the interpreted interface.
    """
    first = re.search(r'^( *)p\.hpipm_options\.mu0 = ', source, re.MULTILINE)
    mode = re.search(r'p\.hpipm_options\.mode = (\d+);', source)
    if first is None or mode is None:
        return source
    fill = (f'{first.group(1)}d_ocp_qp_ipm_arg_set_default((enum hpipm_mode) {mode.group(1)}, '
            '&p.hpipm_options);\n')
    return source[:first.start()] + fill + source[first.start():]


class CompiledFunction:
    """A generated casadi Function called on buffers of its own.

    Write the inputs into ``inputs[i]`` (the nonzeros of input ``i``, casadi's column-major
    order), call, read ``outputs[i]``. The buffers are reused by every call: copy a result
    that must outlive the next call.

    Parameters
    ----------
    so : path
        Library from ``build_cached``.
    fn : casadi.Function
        The Function it was generated from (its name and the sizes of its inputs and outputs).
    """

    def __init__(self, so, fn: ca.Function):
        self.name = fn.name()
        lib = ctypes.CDLL(str(so))
        self._lib = lib   # keeps the library loaded
        sizes = [ctypes.c_longlong() for _ in range(4)]
        getattr(lib, f'{self.name}_work')(*[ctypes.byref(s) for s in sizes])
        n_arg, n_res, n_iw, n_w = (max(s.value, 1) for s in sizes)
        self.inputs = [np.zeros(fn.nnz_in(i)) for i in range(fn.n_in())]
        self.outputs = [np.zeros(fn.nnz_out(i)) for i in range(fn.n_out())]
        self._iw = np.zeros(n_iw, dtype=np.int64)
        self._w = np.zeros(n_w)
        self._arg = (ctypes.c_void_p * max(n_arg, fn.n_in()))(
            *[a.ctypes.data for a in self.inputs])
        self._res = (ctypes.c_void_p * max(n_res, fn.n_out()))(
            *[a.ctypes.data for a in self.outputs])
        if hasattr(lib, f'{self.name}_incref'):
            getattr(lib, f'{self.name}_incref')()
        mem = getattr(lib, f'{self.name}_checkout')() if hasattr(
            lib, f'{self.name}_checkout') else 0
        call = getattr(lib, self.name)
        call.argtypes = [ctypes.c_void_p] * 4 + [ctypes.c_int]
        call.restype = ctypes.c_int
        self._call = call
        self._args = (ctypes.addressof(self._arg), ctypes.addressof(self._res),
                      self._iw.ctypes.data, self._w.ctypes.data, mem)

    def __call__(self) -> bool:
        """Evaluate on ``inputs`` into ``outputs``; False when the generated code reports a
        failure (e.g. a QP solver's, whose outputs are then not to be used)."""
        return self._call(*self._args) == 0


__all__ = ['CASADI_DIR', 'HPIPM_FLAGS', 'CompiledFunction', 'build_cached', 'hpipm_defaults']
