"""Two kinds of substitution the plugin makes into LeRobot at run time, each in one place.

- `child_replaced`: a submodule of a module swapped for the duration of a block (the policy acting with its
  EMA network, the uncertainty's K-weight-set U-Net inside LeRobot's sampler);
- `running_modules`: where a LeRobot script's module lives in this process, so its functions can be wrapped
  (`train_hooks`, `eval_hooks`).
"""

import contextlib
import sys
from collections.abc import Iterator
from types import ModuleType

from torch import nn


@contextlib.contextmanager
def child_replaced(parent: nn.Module, name: str, child: nn.Module) -> Iterator[None]:
    """`parent.<name>` is `child` inside the block and the original again after it, even on an exception."""
    original = parent._modules[name]
    parent._modules[name] = child
    try:
        yield
    finally:
        parent._modules[name] = original


def running_modules(module_name: str) -> list[ModuleType]:
    """The module `module_name` if it is imported, and `__main__` if it is that module run as the program
    (`python -m ...`, torchrun), which Python loads as a second copy."""
    modules = [sys.modules[module_name]] if module_name in sys.modules else []
    main = sys.modules.get("__main__")
    if getattr(getattr(main, "__spec__", None), "name", None) == module_name:
        modules.append(main)
    return modules
