"""The datasets' public classes, made lazily: with a torch `Dataset` base when torch imports
(and `MPIFLOW_NO_TORCH` is not set), as plain Python classes otherwise."""

from __future__ import annotations

import os
from typing import Dict, Tuple

_MADE: Dict[str, type] = {}


def dataset_class(impl: type, name: str, module: str, torch_base: str) -> type:
    """`name`: `impl` with `torch.utils.data.<torch_base>` as a second base where torch is
    available; made once per name."""
    if name in _MADE:
        return _MADE[name]
    bases: Tuple[type, ...] = (impl,)
    if os.environ.get("MPIFLOW_NO_TORCH", "") not in ("1", "true", "yes"):
        try:
            import torch.utils.data as tud

            bases = (impl, getattr(tud, torch_base))
        except Exception:
            pass
    cls = type(name, bases, {"__module__": module, "__doc__": impl.__doc__})
    cls.__qualname__ = name
    _MADE[name] = cls
    return cls
