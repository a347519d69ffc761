"""Whether a module's weights are still those something was derived from.

What inference derives from weights (batch norms folded into convolutions, weights packed for the
C kernels, a cloud's encoding) is kept until a weight changes: in place (an optimiser's step, a
load), by a tensor put in anew, or by a module put in or taken out. In-place changes made through
``.data`` (``p.data.mul_(2)``) are not seen: they bypass the version counter, as autograd's own
checks; change weights under ``torch.no_grad()`` instead.
"""

from __future__ import annotations

import operator
import threading
import weakref
from collections.abc import Callable
from typing import TypeVar

from torch import Tensor, nn

T = TypeVar("T")

__all__ = ["WeightsState", "Derived", "module_tensors"]

_TREES: "weakref.WeakKeyDictionary[nn.Module, tuple[list, list]]" = weakref.WeakKeyDictionary()


def module_tensors(module: nn.Module) -> list[Tensor]:
    """Each parameter and buffer of every module of ``module``. The tree of modules is kept per
    module and walked anew only when a module has been put in or taken out: a check runs on every
    call of a small cloud, where walking a network's modules costs as much as some of its kernels."""
    kept = _TREES.get(module)
    if kept is None or any(tuple(children.values()) != before for children, before in kept[0]):
        modules = list(module.modules())
        kept = ([(m._modules, tuple(m._modules.values())) for m in modules],
                [table for m in modules for table in (m._parameters, m._buffers)])
        _TREES[module] = kept
    return [t for table in kept[1] for t in table.values() if t is not None]


class WeightsState:
    """The tensors of some modules as they are now: which they are, each one's version (bumped by
    every in-place change) and storage address."""

    def __init__(self, modules: list[nn.Module]):
        self.tensors = [t for m in modules for t in module_tensors(m)]
        self.versions = [t._version for t in self.tensors]
        self.addresses = [t.data_ptr() for t in self.tensors]

    def holds(self, modules: list[nn.Module]) -> bool:
        """Whether ``modules`` hold these tensors still, unchanged since."""
        now = [t for m in modules for t in module_tensors(m)]
        return (len(now) == len(self.tensors) and all(map(operator.is_, now, self.tensors))
                and [t._version for t in now] == self.versions and [t.data_ptr() for t in now] == self.addresses)


class Derived:
    """What inference derives from each module's weights (e.g. its layers folded and packed), kept
    per module until the conditions it was made for or the module's weights change. Kept beside the
    modules, not in them: a module pickles and copies without it."""

    def __init__(self):
        self._kept: "weakref.WeakKeyDictionary[nn.Module, tuple]" = weakref.WeakKeyDictionary()
        self._lock = threading.RLock()  # a field's views ask from several threads at once

    def state(self, module: nn.Module) -> WeightsState | None:
        """The weights ``module`` had when what is kept for it was made (checked unchanged by every
        :meth:`get` since); None where nothing is kept."""
        with self._lock:
            kept = self._kept.get(module)
        return None if kept is None else kept[1]

    def get(self, module: nn.Module, conditions: tuple, make: Callable[[], T]) -> T:
        """What ``make()`` made for ``module`` under ``conditions``, made anew where those or the
        module's weights changed since."""
        with self._lock:
            kept = self._kept.get(module)
            if kept is None or kept[0] != conditions or not kept[1].holds([module]):
                kept = self._kept[module] = (conditions, WeightsState([module]), make())
            return kept[2]
