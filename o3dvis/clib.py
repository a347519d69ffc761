"""The package's C code: shared libraries built by the package's build (``setup.py``), installed
beside their Python modules and called through ``ctypes``, which releases the GIL.

Each library is built in variants, one per instruction set (:data:`VARIANTS`): a baseline, and on
x86-64 one for AVX2 with FMA, one for AVX-512 with bfloat16 dot products and one that adds AMX
tiles. At import the widest variant built that this CPU runs is loaded; nothing is compiled at run
time and nothing outside the package is loaded. ``O3DVIS_NATIVE=0`` in the environment turns the
libraries off and ``O3DVIS_NATIVE=<variant>`` picks one. Where none is loaded (no C compiler at install time), the
callers run their Python fallbacks, with one warning a process: at ``import o3dvis`` (:func:`warn_unbuilt`) where
the package was installed without them.

This module imports nothing of the package: ``setup.py`` reads :data:`VARIANTS` from it.
"""

from __future__ import annotations

import ctypes
import importlib.machinery
import importlib.util
import os
import platform
import threading
import warnings
from dataclasses import dataclass

__all__ = ["LIBRARIES", "VARIANTS", "X86_64_ARGS", "Variant", "built_variants", "cpu_flags", "cpu_name", "is_x86",
           "load", "runnable_variants", "warn_unbuilt"]


@dataclass(frozen=True)
class Variant:
    """One build of the libraries.

    Attributes:
        compile_args: the C compiler's flags for it (GCC and Clang spelling).
        cpu_flags: the CPU features (as ``/proc/cpuinfo`` names them) it needs.
    """

    compile_args: tuple[str, ...]
    cpu_flags: frozenset[str]


# narrowest first; a library module ``<name>_<variant>`` per variant built. The compilers' own
# default target may be wider than the baseline: on x86-64 every variant adds X86_64_ARGS
VARIANTS: dict[str, Variant] = {
    "base": Variant((), frozenset()),
    "avx2": Variant(("-mavx2", "-mfma"), frozenset({"avx2", "fma"})),
    "avx512bf16": Variant(("-mavx2", "-mfma", "-mavx512f", "-mavx512bf16"),
                          frozenset({"avx2", "fma", "avx512f", "avx512_bf16"})),
    "amx": Variant(("-mavx2", "-mfma", "-mavx512f", "-mavx512bf16", "-mamx-tile", "-mamx-bf16"),
                   frozenset({"avx2", "fma", "avx512f", "avx512_bf16", "amx_tile", "amx_bf16"})),
}
X86_64_ARGS = ("-march=x86-64", "-mtune=generic")
# the libraries the package's build makes, as modules without their variant
LIBRARIES = ("o3dvis.nn._kernels", "o3dvis.apps._delaunay")
# what torch's CPU capability implies, where /proc/cpuinfo is not there to ask
_CAPABILITY_FLAGS = {"AVX2": {"avx2", "fma"}, "AVX512": {"avx2", "fma", "avx512f"}}


def is_x86() -> bool:
    """Whether this machine's instruction set is x86-64 (only the baseline is built elsewhere)."""
    return platform.machine().lower() in ("x86_64", "amd64")


def cpu_flags() -> frozenset[str]:
    """The CPU features this process may use: the kernel's ``/proc/cpuinfo`` flags (which leave
    out what the operating system does not enable), else what torch's CPU capability implies."""
    try:
        with open("/proc/cpuinfo") as f:
            line = next((line for line in f if line.startswith("flags")), "")
        return frozenset(line.partition(":")[2].split())
    except OSError:
        import torch

        return frozenset(_CAPABILITY_FLAGS.get(torch.backends.cpu.get_cpu_capability(), ()))


def cpu_name() -> str:
    """The CPU's model name as ``/proc/cpuinfo`` gives it, else the platform's processor string
    (empty where neither says)."""
    try:
        with open("/proc/cpuinfo") as f:
            line = next((line for line in f if line.startswith("model name")), "")
        if line:
            return line.partition(":")[2].strip()
    except OSError:
        pass
    return platform.processor()


def runnable_variants() -> list[str]:
    """The variants this CPU runs, narrowest first."""
    flags = cpu_flags()
    return [name for name, v in VARIANTS.items() if (name == "base" or is_x86()) and v.cpu_flags <= flags]


def built_variants(module: str) -> list[str]:
    """The variants of the library ``module`` (e.g. ``"o3dvis.nn._kernels"``) that the package's
    build made, narrowest first; found as files, without importing the module's package."""
    package, _, name = module.rpartition(".")
    spec = importlib.util.find_spec(package)
    folders = (spec.submodule_search_locations or []) if spec is not None else []
    return [variant for variant in VARIANTS
            if any(os.path.isfile(os.path.join(folder, f"{name}_{variant}{suffix}"))
                   for folder in folders for suffix in importlib.machinery.EXTENSION_SUFFIXES)]


_warned = threading.Lock()


def _warn(reason: str) -> None:
    """Warns once a process that the Python fallbacks run instead of the C code."""
    if _warned.acquire(blocking=False):
        warnings.warn(f"o3dvis runs without its C code ({reason}): queries run their per-view steps as torch "
                      "ops and triangulations on scipy's Qhull, which is slower", RuntimeWarning, stacklevel=3)


def _unbuilt(modules: list[str]) -> str:
    """The reason to warn with where ``modules`` were not built."""
    return (f"not built: {', '.join(modules)}; the package was installed without a C compiler; reinstall it where "
            "there is one, bypassing pip's cache of the wheel built without one (pip install --no-cache-dir "
            "--force-reinstall o3dvis)")


def warn_unbuilt() -> None:
    """Warns, once a process, where the package was installed without some of its libraries (unless
    ``O3DVIS_NATIVE=0`` turns them off): ``import o3dvis`` calls it, which loads none of them."""
    missing = [module for module in LIBRARIES if not built_variants(module)]
    if missing and os.environ.get("O3DVIS_NATIVE", "") != "0":
        _warn(_unbuilt(missing))


def load(module: str, signatures: dict[str, tuple[list, object]], variant: str | None = None) -> ctypes.CDLL | None:
    """The library ``module`` (e.g. ``"o3dvis.nn._kernels"``) as the package's build made it: its
    widest variant built, up to ``variant``, that this CPU runs.

    Args:
        module: the library's module name, without the variant.
        signatures: ``{function: (argument types, result type)}`` of the functions called.
        variant: the widest variant to load; None: the one ``O3DVIS_NATIVE`` names, else any.

    Returns:
        The library, its variant's name in its ``variant`` attribute; or None (with a warning, once
        a process) where the libraries are turned off, were not built, or this CPU runs none of
        the variants asked for.
    """
    setting = os.environ.get("O3DVIS_NATIVE", "")
    if variant is None and setting == "0":
        _warn("turned off by O3DVIS_NATIVE=0")
        return None
    if variant is None and setting not in ("", "1"):
        if setting not in VARIANTS:
            _warn(f"O3DVIS_NATIVE={setting} names no variant; use 0 or one of {', '.join(VARIANTS)}")
            return None
        variant = setting
    runnable = runnable_variants()
    if variant is not None and variant not in runnable:
        _warn(f"this CPU cannot run the {variant} variant")
        return None
    for name in reversed(runnable if variant is None else runnable[:runnable.index(variant) + 1]):
        spec = importlib.util.find_spec(f"{module}_{name}")
        if spec is None or spec.origin is None:
            continue
        try:
            library = ctypes.CDLL(spec.origin)
            for function, (args, result) in signatures.items():
                getattr(library, function).argtypes, getattr(library, function).restype = args, result
        except (OSError, AttributeError) as e:
            _warn(f"{spec.origin} could not be loaded: {e}")
            return None
        library.variant = name
        return library
    _warn(_unbuilt([module]))
    return None
