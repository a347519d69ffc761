"""The package's C sources as libraries: built on first use with the system's C compiler (``$CC``,
else ``cc``) for this CPU, kept in a cache folder (``$O3DVIS_CACHE``, else
``$XDG_CACHE_HOME/o3dvis`` or ``~/.cache/o3dvis``) and called through ``ctypes``, which releases
the GIL. Where no compiler is found, or with ``O3DVIS_NATIVE=0`` in the environment, the callers
run their Python fallback instead, with a warning.
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import platform
import subprocess
import tempfile
import threading
import warnings
from pathlib import Path

__all__ = ["CLibrary"]


def _cache_dir() -> Path:
    if os.environ.get("O3DVIS_CACHE"):
        return Path(os.environ["O3DVIS_CACHE"])
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "o3dvis"


def _cpu() -> str:
    """What identifies this CPU's instruction set (the libraries are built with ``-march=native``)."""
    try:
        with open("/proc/cpuinfo") as f:
            flags = next((line for line in f if line.startswith(("flags", "Features"))), "")
    except OSError:
        flags = ""
    return f"{platform.machine()} {platform.processor()} {flags}"


class CLibrary:
    """One C source of the package, built and loaded once per process.

    Args:
        source: the ``.c`` file.
        flags: the compiler's flags (``-march=native`` is added where the compiler knows it).
        signatures: ``{name: (argument types, result type)}`` of the functions called.
        fallback: what the callers do without the library, for the warning.
    """

    def __init__(self, source: Path, flags: list[str], signatures: dict[str, tuple[list, object]],
                 fallback: str):
        self.source, self.flags, self.signatures, self.fallback = source, flags, signatures, fallback
        self._lock = threading.Lock()
        self._library: list[ctypes.CDLL | None] = []  # once tried: the library, or None

    def _build(self) -> ctypes.CDLL:
        """Loads the library, compiling it into the cache folder first if it is not there (or is
        not a library: a build cut short)."""
        compiler = os.environ.get("CC", "cc")
        key = hashlib.sha256(b"\0".join([self.source.read_bytes(), compiler.encode(), " ".join(self.flags).encode(),
                                         _cpu().encode()])).hexdigest()[:16]
        folder = _cache_dir()
        path = folder / f"{self.source.stem}-{key}.so"
        if path.exists():
            try:
                return ctypes.CDLL(str(path))
            except OSError:  # a truncated or foreign file: built anew below
                path.unlink(missing_ok=True)
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory(dir=folder) as tmp:
            built = Path(tmp) / path.name
            errors = []
            for arch in (["-march=native"], []):  # some compilers know no -march=native
                run = subprocess.run([compiler, *self.flags, *arch, str(self.source), "-o", str(built), "-lm"],
                                     capture_output=True, text=True, timeout=300)
                if run.returncode == 0:
                    break
                errors.append(run.stderr.strip())
            else:
                raise OSError("\n".join(errors))
            os.replace(built, path)  # atomic: another process sees the whole file or none
        return ctypes.CDLL(str(path))

    def get(self) -> ctypes.CDLL | None:
        """The loaded library, or None (with a warning, once) where it cannot be had."""
        with self._lock:
            if not self._library:
                library, reason = None, "the C kernels are turned off (O3DVIS_NATIVE=0)"
                if os.environ.get("O3DVIS_NATIVE", "1") != "0":
                    try:
                        library = self._build()
                        for name, (args, result) in self.signatures.items():
                            function = getattr(library, name)
                            function.argtypes, function.restype = args, result
                    except (OSError, AttributeError, RuntimeError, KeyError, subprocess.SubprocessError) as e:
                        library, reason = None, f"the C kernels could not be built or loaded: {e}"
                if library is None:
                    warnings.warn(f"o3dvis: {self.fallback}; {reason}", RuntimeWarning)
                self._library.append(library)
            return self._library[0]
