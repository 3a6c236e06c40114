"""Import the test bed script (deploy/testbed/bgt_testbed.py), which is a file, not a package."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType

REPO = Path(__file__).resolve().parents[2]
SCRIPT = REPO / "deploy" / "testbed" / "bgt_testbed.py"


def load_testbed(name: str = "bgt_testbed") -> ModuleType:
    """Load the script as module `name` (registered in sys.modules, as its dataclasses need)."""
    spec = importlib.util.spec_from_file_location(name, SCRIPT)
    assert spec is not None
    assert spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    spec.loader.exec_module(mod)
    return mod
