"""The package as a whole: the public functions' docstrings render, every module defines what its
``__all__`` names, and the runtime never imports the training code."""

from __future__ import annotations

import pydoc

import pytest

import o3dvis
from o3dvis.cameras import as_views


@pytest.mark.parametrize("func", [o3dvis.hidden_point_removal_neural, o3dvis.select_visible,
                                  o3dvis.NeuralVisibility, o3dvis.NeuralVisibility.pretrained,
                                  o3dvis.NeuralVisibility.encode, o3dvis.VisibilityField.query,
                                  o3dvis.VisibilityField.probabilities, o3dvis.load_model, as_views])
def test_docstrings_render_with_args_and_returns(func):
    text = pydoc.render_doc(func, renderer=pydoc.plaintext)
    assert "Args:" in text
    if func is not o3dvis.NeuralVisibility:
        assert "Returns:" in text


def test_the_runtime_never_imports_training_code():
    """Every module outside o3dvis.training, o3dvis.evaluation and the command line imports without
    either of the two."""
    import subprocess
    import sys
    from pathlib import Path

    root = Path(o3dvis.__file__).parent
    modules = sorted(".".join(("o3dvis",) + p.relative_to(root).with_suffix("").parts).removesuffix(".__init__")
                     for p in root.rglob("*.py")
                     if p.relative_to(root).parts[0] not in ("training", "evaluation", "cli", "__main__.py"))
    assert {"o3dvis", "o3dvis.neural", "o3dvis.field", "o3dvis.dropins", "o3dvis.apps.normals"} <= set(modules)
    code = ("import importlib, sys\n"
            f"for name in {modules!r}:\n"
            "    importlib.import_module(name)\n"
            "print(sorted(m for m in sys.modules if m.startswith(('o3dvis.training', 'o3dvis.evaluation'))))")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300,
                         cwd=root.parent)
    assert run.returncode == 0, run.stderr
    assert run.stdout.strip() == "[]"


def test_every_module_defines_what_its_all_names():
    import importlib
    import pkgutil

    missing = []
    for info in pkgutil.walk_packages(o3dvis.__path__, "o3dvis."):
        name = info.name.rsplit(".", 1)[-1]
        if name == "__main__" or name.startswith("_kernels") or name.startswith("_delaunay"):
            continue  # the command line runs on import; native libraries are not Python modules
        module = importlib.import_module(info.name)
        missing += [f"{info.name}.{n}" for n in getattr(module, "__all__", ()) if not hasattr(module, n)]
    assert not missing, f"__all__ names what the module does not define: {missing}"
