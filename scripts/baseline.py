"""Another FlowBSDF checkout's `bake` package, imported beside this one as `bake_baseline`: the
before-and-after benchmarks (scripts/tables_speed.py, scripts/bake_speed.py) run both in one
process, in turns, so that a load spike hits both."""
import importlib.util
import sys
from pathlib import Path


def import_baseline(checkout):
    """The package bake/ of `checkout`, as the module `bake_baseline` (its submodules import as
    bake_baseline.<name>)."""
    init = Path(checkout) / "bake" / "__init__.py"
    spec = importlib.util.spec_from_file_location("bake_baseline", init, submodule_search_locations=[str(init.parent)])
    module = importlib.util.module_from_spec(spec)
    sys.modules["bake_baseline"] = module
    spec.loader.exec_module(module)
    return module
