"""Builds the package's C libraries (see ``o3dvis/clib.py``): each for a baseline CPU and, on
x86-64, for AVX2 with FMA, for AVX-512 with bfloat16 dot products and for AMX tiles. They are
optional: where one cannot be built (no C compiler, or one that lacks an instruction set's flags)
the install goes on, and the package runs its Python fallbacks. The rest of the metadata is in pyproject.toml.

The libraries use no Python API (``ctypes`` calls them), so one wheel serves every CPython the
package supports: they are built as stable-ABI (``abi3``) files and the wheel is tagged
``cp310-abi3-<platform>``. A wheel that holds none of them is pure Python, ``py3-none-any``: its tag
does not claim compiled code it lacks.
"""

import runpy
import sysconfig
from pathlib import Path

from setuptools import Extension, setup
from setuptools.command.bdist_wheel import bdist_wheel
from setuptools.command.build_ext import build_ext

_HERE = Path(__file__).resolve().parent
_CLIB = runpy.run_path(str(_HERE / "o3dvis" / "clib.py"))
_KERNELS = "o3dvis/nn/csrc"
# module: (sources, headers, compiler flags, variants), paths relative to this file, as setuptools
# takes them. The kernels are one library built from the C files of their folder, by concept, that
# share one header. -ffp-contract=off: rounding follows the Python fallbacks' op order; the
# kernels' loops vectorise with no errno and no traps. The Delaunay sweep's integer predicates and
# branches run no faster with wider vectors: baseline only
_LIBRARIES = {
    "o3dvis.nn._kernels": (sorted(p.relative_to(_HERE).as_posix() for p in (_HERE / _KERNELS).glob("*.c")),
                           [f"{_KERNELS}/kernels.h"],
                           ["-O3", "-fno-math-errno", "-fno-trapping-math", "-ffp-contract=off"],
                           tuple(_CLIB["VARIANTS"])),
    "o3dvis.apps._delaunay": (["o3dvis/apps/delaunay.c"], [], ["-O3", "-ffp-contract=off"], ("base",)),
}
# free-threaded CPython before 3.15 has no stable ABI
_ABI3 = not sysconfig.get_config_var("Py_GIL_DISABLED")


def _extensions() -> list[Extension]:
    x86 = _CLIB["is_x86"]()
    variants = {name: [*(_CLIB["X86_64_ARGS"] if x86 else ()), *variant.compile_args]
                for name, variant in _CLIB["VARIANTS"].items() if name == "base" or x86}
    return [Extension(f"{module}_{name}", sources, depends=headers,
                      extra_compile_args=["-pthread", *flags, *variants[name]], extra_link_args=["-pthread"],
                      libraries=["m"], optional=True, py_limited_api=_ABI3)
            for module, (sources, headers, flags, built) in _LIBRARIES.items() for name in built if name in variants]


class _BuildExt(build_ext):
    """build_ext that, building in place, removes each library's files under other suffixes: an
    interpreter-specific name, which the import system finds before the abi3 one."""

    def copy_extensions_to_source(self) -> None:
        super().copy_extensions_to_source()
        for ext in self.extensions:
            built = Path(self.get_ext_fullpath(ext.name))  # in place, as self.inplace is set again
            for other in built.parent.glob(f"{built.name.partition('.')[0]}.*") if built.is_file() else ():
                if other != built and other.suffix in (".so", ".pyd"):
                    other.unlink()


class _Wheel(bdist_wheel):
    """A wheel tagged by what its build made: pure Python where none of the optional libraries
    was built, else for this platform (abi3 where the interpreter has a stable ABI)."""

    def get_tag(self) -> tuple[str, str, str]:
        # called after the build, for the wheel's name and its WHEEL file
        built = self.get_finalized_command("build_ext").get_outputs()
        self.root_is_pure = not any(Path(library).is_file() for library in built)
        return super().get_tag()


setup(ext_modules=_extensions(), cmdclass={"build_ext": _BuildExt, "bdist_wheel": _Wheel},
      options={"bdist_wheel": {"py_limited_api": "cp310"} if _ABI3 else {}})
