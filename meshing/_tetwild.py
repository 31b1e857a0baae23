"""Adapter around pytetwild (fTetWild): tetrahedralise a triangle soup, reproducibly.

Only this module imports pytetwild. fTetWild keeps every input triangle inside an envelope
of half-width ``epsilon`` and returns its whole background mesh when filtering is disabled,
so that the caller decides which tets are inside which region.

fTetWild is not deterministic as shipped, even on one thread: it inserts the input triangles
in an order shuffled by a generator seeded from ``std::random_device`` (``sort_input_faces``
in its ``TriangleInsertion.cpp``; pytetwild 0.4.2 does not expose its ``not_sort_input``
switch), and a static generator (``floatTetWild::Random``, seed 42) keeps its state from one
call to the next. This module makes it reproducible:

- the wrapper's call to ``std::random_device::_M_getval`` is redirected to a function that
  returns a fixed seed (its slot in the library's global offset table is overwritten; x86-64
  Linux only, where the slot lies outside the read-only RELRO segment);
- the static generator's initialisation guard is cleared before each call, so that it starts
  again from its seed;
- fTetWild runs in a fresh Python process (``python -m meshing._tetwild``), because it also
  iterates over containers whose order follows heap addresses: in one process, a second
  call gives the same tets in another order with nodes moved by ~1e-7 mm; fresh processes
  give byte-identical meshes for a given thread count (not across counts: a label map of
  the demo gives 3507 tets on one thread and 3511 on two).

Where the redirection cannot be installed (another platform or build), meshing still works
and :func:`reproducible` says why the mesh will vary from run to run.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import struct
import sys
import tempfile
import warnings
from pathlib import Path

import numpy as np

from imaging.atomic import write_atomic_with
from meshing._fresh import run_module

SEED = 20211  # returned to fTetWild in place of a hardware random number
_GETVAL = "_ZNSt13random_device9_M_getvalEv"
_GUARD = "_ZGVZN12floatTetWild6Random4nextEiiE3gen"  # guard of Random::next's static gen
_HOOK: list = []  # keeps the installed callback alive; [reason] when it could not be
_STATE: dict[str, str | None] = {}


def _wrapper_library() -> Path:
    import pytetwild

    found = sorted(Path(pytetwild.__file__).parent.glob("PyfTetWildWrapper*.so"))
    if not found:
        raise OSError("pytetwild's compiled wrapper (PyfTetWildWrapper*.so) was not found")
    return found[0]


def _got_slots(path: Path, symbol: str) -> list[int]:
    """Offsets of the global-offset-table slots through which an ELF64 library calls
    ``symbol`` (its JUMP_SLOT / GLOB_DAT relocations)."""
    data = path.read_bytes()
    if data[:5] != b"\x7fELF\x02" or data[5] != 1:
        raise OSError(f"{path.name} is not a little-endian ELF64 library")
    shoff, = struct.unpack_from("<Q", data, 0x28)
    shentsize, shnum, shstrndx = struct.unpack_from("<HHH", data, 0x3A)
    heads = [struct.unpack_from("<IIQQQQIIQQ", data, shoff + i * shentsize) for i in range(shnum)]

    def cstr(offset: int) -> str:
        return data[offset:data.index(b"\0", offset)].decode()

    names = {cstr(heads[shstrndx][4] + h[0]): h for h in heads}
    sym_off, str_off = names[".dynsym"][4], names[".dynstr"][4]
    slots = []
    for sec in (".rela.plt", ".rela.dyn"):
        if sec not in names:
            continue
        off, size = names[sec][4], names[sec][5]
        for k in range(size // 24):
            r_offset, r_info, _ = struct.unpack_from("<QQq", data, off + 24 * k)
            st_name, = struct.unpack_from("<I", data, sym_off + 24 * (r_info >> 32))
            if cstr(str_off + st_name) == symbol:
                slots.append(r_offset)
    return slots


def _load_bias(path: Path) -> int:
    """Address at which the loaded library's offset 0 is mapped (from /proc/self/maps)."""
    real = os.path.realpath(path)
    starts = [int(p[0].split("-")[0], 16) for p in
              (line.split() for line in Path("/proc/self/maps").read_text().splitlines())
              if len(p) >= 6 and p[5] == real and int(p[2], 16) == 0]
    if not starts:
        raise OSError(f"{path.name} is not mapped in this process")
    return min(starts)


def _writable(address: int) -> bool:
    """Whether ``address`` lies in a writable mapping of this process (/proc/self/maps)."""
    for line in Path("/proc/self/maps").read_text().splitlines():
        span, perms = line.split()[:2]
        lo, hi = (int(v, 16) for v in span.split("-"))
        if lo <= address < hi:
            return "w" in perms
    return False


def reproducible() -> str | None:
    """Install the fixed seed (once per process); None when fTetWild is reproducible, else
    the reason it is not."""
    if "why" in _STATE:
        return _STATE["why"]
    why = None
    try:
        if sys.platform != "linux" or struct.calcsize("P") != 8:
            raise OSError(f"the seed redirection supports 64-bit Linux only, not {sys.platform}")
        lib_path = _wrapper_library()
        lib = ctypes.CDLL(str(lib_path))  # the already loaded wrapper
        ctypes.c_uint64.in_dll(lib, _GUARD)  # the static generator must be reachable
        slots = _got_slots(lib_path, _GETVAL)
        if not slots:
            raise OSError(f"{lib_path.name} does not call std::random_device")
        bias = _load_bias(lib_path)
        if not all(_writable(bias + slot) for slot in slots):
            raise OSError(f"{lib_path.name}'s offset table is read-only (a full-RELRO build)")
        hook = ctypes.CFUNCTYPE(ctypes.c_uint, ctypes.c_void_p)(lambda _self: SEED)
        address = ctypes.cast(hook, ctypes.c_void_p).value
        for slot in slots:
            ctypes.c_uint64.from_address(bias + slot).value = address
        _HOOK.append(hook)
    except (OSError, ValueError, KeyError) as exc:
        why = f"fTetWild's random seed could not be fixed ({exc}); meshes vary from run to run"
    _STATE["why"] = why
    return why


def _restart_static_generator() -> None:
    lib = ctypes.CDLL(str(_wrapper_library()))
    ctypes.c_uint64.in_dll(lib, _GUARD).value = 0


@contextlib.contextmanager
def _scratch_cwd():
    """Run inside a temporary working directory: fTetWild's inside filter writes a debug
    file ``__tracked_surface.stl`` into the current directory (its winding-number filter
    calls ``get_tracked_surface``, which saves the surface it extracts)."""
    old = os.getcwd()
    with tempfile.TemporaryDirectory(prefix="ftetwild_") as tmp:
        os.chdir(tmp)
        try:
            yield
        finally:
            os.chdir(old)


def _run_ftetwild(v, f, options: dict, sizing) -> tuple[np.ndarray, np.ndarray]:
    """One fTetWild call in this process, with the fixed seed where it can be installed."""
    import pytetwild

    why = reproducible()
    if why is None:
        _restart_static_generator()
    guard = contextlib.nullcontext() if options["disable_filtering"] else _scratch_cwd()
    with guard:
        nodes, tets = pytetwild.tetrahedralize(
            v, f, **options,
            **({} if sizing is None else
               {"bg_vertices": sizing[0], "bg_tets": sizing[1], "bg_values": sizing[2]}),
        )
    return np.asarray(nodes, dtype=np.float64), np.asarray(tets, dtype=np.int64)


def tetrahedralize(
    vertices: np.ndarray,
    faces: np.ndarray,
    *,
    edge_mm: float,
    epsilon_mm: float,
    keep_background: bool = True,
    threads: int = 0,
    optimize_iterations: int = 30,
    stop_energy: float = 20.0,
    sizing: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
    fresh_process: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """Tetrahedral mesh that conforms to all input triangles (within ``epsilon_mm``).

    Parameters
    ----------
    vertices : (n, 3) float, mm
    faces : (m, 3) int; may be non-manifold (several closed or open surfaces)
    edge_mm : float
        Ideal tet edge length, mm.
    epsilon_mm : float
        Envelope half-width: how far the tet faces may deviate from the input, mm.
    keep_background : bool
        Return every tet of the bounding box (True) instead of fTetWild's inside filter
        (False; that filter runs in a temporary working directory, see ``_scratch_cwd``).
    threads : int
        fTetWild's thread count (0: all cores). The mesh does not depend on it.
    optimize_iterations, stop_energy
        fTetWild's optimisation budget: it stops after this many passes or once the worst
        AMIPS energy is below ``stop_energy`` (its default 10; 20 is faster and still gives
        aspect ratios well below 12 here).
    sizing : (points (k, 3), tets (l, 4), edge length (k,) mm), optional
        Background tet mesh giving a spatially varying target edge length. fTetWild applies
        it only after its main optimisation, which works at ``edge_mm`` everywhere: give a
        coarse ``edge_mm`` (the largest size wanted) so that the main passes run on a coarse
        mesh of the whole bounding box, and let the field refine where the tissue is.
    fresh_process : bool
        Run fTetWild in a fresh Python process (default), so that one input gives one mesh,
        byte for byte (see the module docstring); False runs it here (same tets, in an order
        and with rounding that depend on earlier calls).

    Returns
    -------
    nodes : (N, 3) float64, mm
    tets : (M, 4) int64, positively oriented
    """
    v = np.ascontiguousarray(vertices, dtype=np.float64)
    f = np.ascontiguousarray(faces, dtype=np.int32)
    diag = float(np.linalg.norm(v.max(0) - v.min(0)))
    options = dict(
        edge_length_abs=float(edge_mm), epsilon=float(epsilon_mm) / diag, optimize=True,
        simplify=True, num_threads=int(threads), num_opt_iter=int(optimize_iterations),
        stop_energy=float(stop_energy), quiet=True, disable_filtering=bool(keep_background),
    )
    if fresh_process:
        nodes, tets = _in_fresh_process(v, f, options, sizing)
    else:
        nodes, tets = _run_ftetwild(v, f, options, sizing)
    e = nodes[tets[:, 1:]] - nodes[tets[:, :1]]
    neg = np.linalg.det(e) < 0
    tets[neg] = tets[neg][:, [0, 2, 1, 3]]
    return nodes, tets


def _in_fresh_process(v, f, options, sizing) -> tuple[np.ndarray, np.ndarray]:
    with tempfile.TemporaryDirectory(prefix="ftetwild_io_") as tmp:
        src, dst = Path(tmp) / "in.npz", Path(tmp) / "out.npz"
        extra = {} if sizing is None else {"bg_v": sizing[0], "bg_t": sizing[1],
                                           "bg_s": sizing[2]}
        np.savez(src, v=v, f=f, options=np.array(repr(options)), **extra)
        done = run_module("meshing._tetwild", [str(src), str(dst)], dst,
                          what="meshing: fTetWild")
        for line in done.stderr.splitlines():
            if line.startswith("meshing: fTetWild's random seed"):
                warnings.warn(line, RuntimeWarning, stacklevel=3)
        with np.load(dst) as out:
            return out["nodes"], out["tets"]


def _main(src: str, dst: str) -> None:
    import ast

    with np.load(src) as a:
        v, f = a["v"], a["f"]
        options = ast.literal_eval(str(a["options"]))
        sizing = (a["bg_v"], a["bg_t"], a["bg_s"]) if "bg_v" in a else None
    why = reproducible()
    if why is not None:
        print(f"meshing: {why}", file=sys.stderr)
    nodes, tets = _run_ftetwild(v, f, options, sizing)
    write_atomic_with(dst, lambda tmp: np.savez(tmp, nodes=nodes, tets=tets), suffix=".npz")


if __name__ == "__main__":
    _main(*sys.argv[1:3])
