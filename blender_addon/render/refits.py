"""Refits after a file opens: the closure fits an older add-on made, remade from their tables.

Opening a .blend whose fits an older add-on made refits each from its tables (~5 s per
material on 2 idle cores). In the UI that runs in a thread, the older fit rendering meanwhile
(every readable version renders), so a file with many materials opens at once; each group is
rebuilt as its fit is written, and a final render waits for the rest (render_pre). Without a
UI (blender --background, a farm's render) load_post refits before anything renders. This
module sits below node.py: the node hands in how a group is rebuilt and a scene synced
(`refit_later`)."""
from pathlib import Path

import bpy

from .. import deps
from . import binding, derived

_refit = {"thread": None, "tables": [], "done": set(), "errors": {}, "rebuild": None, "sync": None}


def refit_in_thread():
    """Whether refits after a file opens run in a thread (the UI) rather than in load_post."""
    return not bpy.app.background


def stale_fit(tree):
    """Whether the group's fit is of an older version (made by an older add-on) and can be
    refit here: its tables are at hand and the bake module imports."""
    info = binding.read(tree)
    return bool(info.get("has_fit") and not derived.fit_current(info.get("fit_version", 0), info.get("anisotropic", False))
                and info.get("tables")
                and Path(info["tables"]).is_file() and deps.bake_module("export.closure_fit") is not None)


def _refit_worker(tables, done, errors):
    closure_fit = deps.bake_module("export.derived")
    for path in tables:
        try:
            closure_fit.ensure_fit(path)
        except Exception as e:      # noqa: BLE001  (the older fit keeps rendering; the status says why)
            errors[path] = str(e)
        done.add(path)


def refit_later(trees, rebuild, sync):
    """Refit the fits of `trees` (stale: `stale_fit`) in a thread; a timer rebuilds each group
    once its fit file is written (`refit_poll`: rebuild(tree)), then syncs every scene
    (sync(scene)) when all are."""
    import threading
    tables = list(dict.fromkeys(binding.read(t)["tables"] for t in trees))
    if not tables:
        return
    finish_refits()         # (a file opened while another's refits ran: those first)
    done, errors = set(), {}
    thread = threading.Thread(target=_refit_worker, args=(tables, done, errors), name="FlowBSDF refit", daemon=True)
    _refit.update(thread=thread, tables=tables, done=done, errors=errors, rebuild=rebuild, sync=sync)
    print(f"FlowBSDF: remaking {len(tables)} closure fit(s) of an older add-on in the background; "
          "the older fits render until then")
    thread.start()
    if not bpy.app.timers.is_registered(refit_poll):
        bpy.app.timers.register(refit_poll, first_interval=0.5)


def refitting(tree):
    """(done, total) of the refits running when `tree` waits for one, else None."""
    if _refit["thread"] is None or binding.read(tree).get("tables") not in _refit["tables"] or not stale_fit(tree):
        return None
    return len(_refit["done"]), len(_refit["tables"])


def refit_poll():
    """Rebuild the groups whose new fit is written (a bpy timer: None stops it)."""
    done = set(_refit["done"])
    for tree in list(binding.trees()):
        tables = binding.read(tree).get("tables")
        if tables in done and stale_fit(tree):
            if tables in _refit["errors"]:
                print(f"FlowBSDF: could not refit {tree.name} (its older fit renders): {_refit['errors'][tables]}")
                binding.write(tree, {**binding.read(tree), "problems": f"refit failed: {_refit['errors'][tables]}"})
                continue
            try:
                _refit["rebuild"](tree)
            except Exception as e:      # noqa: BLE001
                print(f"FlowBSDF: could not rebuild {tree.name} with its new fit: {e}")
    if len(done) < len(_refit["tables"]):
        return 0.5
    _refit["thread"] = None
    for scene in bpy.data.scenes:
        _refit["sync"](scene)
    return None


def finish_refits():
    """Wait for the refits running and rebuild their groups (before a final render)."""
    thread = _refit["thread"]
    if thread is None:
        return
    thread.join()
    refit_poll()
    if bpy.app.timers.is_registered(refit_poll):
        bpy.app.timers.unregister(refit_poll)
