"""Drives the FlowBSDF panel in a real Blender UI (run by tests/test_ui_blender.py under Xvfb).

    blender --factory-startup --enable-event-simulate --python blender_ui_script.py -- OUT_DIR MATERIAL_FILE

The legacy add-on `flowbsdf` must be installed in BLENDER_USER_SCRIPTS and FLOWBSDF_PYTHON
set. Steps (a timer drives them, the UI draws in between): the Shader Editor with its
sidebar on the FlowBSDF tab and the Properties editor on the Material tab, both at Blender's
default sizes; an unsaved file's Bake is refused; the file is saved, the material baked
from the panel's Bake operator (modal, as a click does) and watched while it runs; after
it, the preview icon; then a Bake whose Python does not exist (the error report). At each stage a screenshot (OUT_DIR/<stage>.png) and every text the
two panels draw, measured in the UI font against the width Blender gives it
(OUT_DIR/<stage>.json). Writes OUT_DIR/result.json and quits.
"""
import json
import os
import sys
import time

import addon_utils
import blf
import bpy

OUT, MATERIAL_FILE = sys.argv[-2], sys.argv[-1]
# Blender 3.4's layout, in pixels at UI scale 1 (measured on its screenshots, a little on the
# safe side): the sidebar's tab strip, a panel's and a box's padding per side, a button's text
# margin per side, a label's, an icon.
TABS, PANEL, BOX, TEXT, LABEL, ICON = 20, 12, 10, 6, 9, 20
SPLIT = 0.4                  # property split: the label's share of the width
result = {"stages": {}, "errors": []}


def text_width(text):
    scale = bpy.context.preferences.system.dpi / 72.0 if not hasattr(bpy.context.preferences.system, "ui_scale") \
        else bpy.context.preferences.system.ui_scale
    blf.size(0, bpy.context.preferences.ui_styles[0].widget.points * scale)
    return blf.dimensions(0, text)[0]


class Layout:
    """Records what a panel draws and the width each item gets (one row shares its width)."""

    def __init__(self, width, out, split=False):
        self.width, self.out, self.use_property_split, self.use_property_decorate = width, out, split, True

    def column(self, align=False):
        return Layout(self.width, self.out, self.use_property_split)

    def box(self):
        return Layout(self.width - 2 * BOX, self.out, self.use_property_split)

    def row(self, align=False):
        return Row(self.width, self.out)

    def _add(self, kind, text, icon, width):
        self.out.append({"kind": kind, "text": text, "icon": bool(icon) and icon != "NONE", "width": width})

    def label(self, text="", icon="NONE", **kw):      # under a property split: in the value column
        self._add("label", text, icon, self.width * (1 - SPLIT) if self.use_property_split else self.width)

    def operator(self, idname, text=None, icon="NONE", **kw):
        mod, name = idname.split(".")
        label = text if text is not None else getattr(getattr(bpy.ops, mod), name).get_rna_type().name
        self._add("operator", label, icon, self.width)
        return Props()

    def prop(self, data, attr, text=None, icon="NONE", **kw):
        rna = data.bl_rna.properties[attr]
        name = rna.name if text is None else text
        value = getattr(data, attr)
        shown = None
        if rna.type == "ENUM" and not kw.get("expand"):
            shown = rna.enum_items[value].name if value in rna.enum_items else ""
        elif rna.type == "STRING" and rna.subtype not in ("FILE_PATH", "DIR_PATH"):
            shown = value
        if rna.type == "BOOLEAN":         # under a property split, indented in the value column
            self._add("checkbox", name, "CHECKBOX", self.width * (1 - SPLIT) - 2 * TEXT if self.use_property_split
                      else self.width)
        elif self.use_property_split:
            self._add("prop label", name, "NONE", self.width * SPLIT)
            if shown:
                self._add("prop value", shown, "NONE", self.width * (1 - SPLIT) - ICON * (rna.type == "ENUM"))
        elif shown:
            self._add("prop value", f"{name}: {shown}" if name else shown, "NONE", self.width)

    def progress(self, factor=0.0, type="BAR", text=""):
        self._add("progress", text, "NONE", self.width)

    def template_icon(self, icon_value=0, scale=1.0):
        result.setdefault("icons", []).append(icon_value)


class Row(Layout):
    def __init__(self, width, out):
        super().__init__(width, [])
        self.parent_out = out
        out.append({"kind": "row", "items": self.out, "width": width})


class Props:
    def __setattr__(self, key, value):
        pass


def flatten(items, width=None):
    for item in items:
        if item["kind"] == "row":
            n = max(len(item["items"]), 1)
            for sub in item["items"]:
                yield {**sub, "width": item["width"] / n}
        else:
            yield item


def check(stage, area, panel_cls, tabs):
    """Every text the panel draws and whether it fits its place."""
    region = next(r for r in area.regions if r.type == ("UI" if tabs else "WINDOW"))
    width = region.width - (TABS if tabs else 0) - 2 * PANEL
    out = []
    ctx = bpy.context.copy()
    ctx.update(area=area, region=region, space_data=area.spaces.active)
    with bpy.context.temp_override(**ctx):
        panel_cls.draw(type("P", (), {"layout": Layout(width, out)})(), bpy.context)
    rows = []
    for item in flatten(out):
        need = text_width(item["text"]) + (ICON if item["icon"] else 0) + \
            (2 * TEXT if item["kind"] in ("operator", "progress", "prop value") else LABEL)
        rows.append({**item, "need": round(need, 1), "fits": need <= item["width"] + 0.5})
    result["stages"].setdefault(stage, {})[panel_cls.bl_idname] = {"region_width": region.width, "items": rows}


def screenshot(stage):
    win = bpy.context.window_manager.windows[0]
    path = os.path.join(OUT, f"{stage}.png")
    with bpy.context.temp_override(window=win, area=win.screen.areas[0]):
        bpy.ops.screen.screenshot(filepath=path)
    return path


def setup():
    addon_utils.enable("flowbsdf", default_set=True)
    mat = bpy.data.materials.new("MilitaryGreen")
    mat.use_nodes = True
    s = mat.flowbsdf
    s.enabled, s.bake_quality = True, "DRAFT"
    if os.path.isfile(MATERIAL_FILE):
        s.source_kind, s.filepath = "FILE", MATERIAL_FILE
    else:
        s.source_kind, s.analytic_preset = "ANALYTIC", "PLASTIC"
    cube = bpy.data.objects["Cube"]
    cube.data.materials.clear()
    cube.data.materials.append(mat)
    bpy.context.view_layer.objects.active = cube
    win = bpy.context.window_manager.windows[0]
    view = next(a for a in win.screen.areas if a.type == "VIEW_3D")
    view.type = "NODE_EDITOR"
    view.spaces.active.tree_type = "ShaderNodeTree"
    view.spaces.active.show_region_ui = True
    props = next(a for a in win.screen.areas if a.type == "PROPERTIES")
    props.spaces.active.context = "MATERIAL"
    return win, view, props


def steps():
    """A generator: each yield waits that many seconds (the UI redraws meanwhile)."""
    import flowbsdf.artist.panels as panels
    win = bpy.context.window_manager.windows[0]
    win.event_simulate(type="ESC", value="PRESS", x=10, y=10)        # close the splash
    win.event_simulate(type="ESC", value="RELEASE", x=10, y=10)
    yield 0.5
    win, view, props = setup()
    region = next(r for r in view.regions if r.type == "UI")
    x, y = region.x + region.width // 2, region.y + region.height // 2
    for _ in range(8):                  # Ctrl+Wheel over the sidebar: to the last tab (FlowBSDF)
        win.event_simulate(type="MOUSEMOVE", value="NOTHING", x=x, y=y)
        win.event_simulate(type="WHEELDOWNMOUSE", value="PRESS", x=x, y=y, ctrl=True)
        yield 0.2
    yield 1.0

    def stage(name):
        """Check the texts, scroll the Material tab down to the FlowBSDF panel, redraw, screenshot."""
        check(name, view, panels.FLOWBSDF_PT_node_editor, tabs=True)
        check(name, props, panels.FLOWBSDF_PT_material, tabs=False)
        window = next(r for r in props.regions if r.type == "WINDOW")
        for _ in range(30):
            win.event_simulate(type="MOUSEMOVE", value="NOTHING", x=window.x + 50, y=window.y + 50)
            win.event_simulate(type="WHEELDOWNMOUSE", value="PRESS", x=window.x + 50, y=window.y + 50)
        yield 0.5
        screenshot(name)

    def bake():
        ctx = {"window": win, "area": view, "region": region, "material": bpy.data.materials["MilitaryGreen"]}
        with bpy.context.temp_override(**ctx):
            return bpy.ops.flowbsdf.bake("INVOKE_DEFAULT", only_active=True)

    result["material_panel_options"] = sorted(getattr(panels.FLOWBSDF_PT_material, "bl_options", ()))
    try:
        result["unsaved_bake"] = sorted(bake())
    except RuntimeError as e:           # the operator's error report, raised into a script
        result["unsaved_bake"] = str(e)
    result["unsaved_message"] = bpy.context.window_manager.flowbsdf_job.message
    yield 0.5
    yield from stage("unsaved")
    bpy.ops.wm.save_as_mainfile(filepath=os.path.join(OUT, "project", "shot.blend"))
    bpy.context.window_manager.flowbsdf_job.message = ""
    yield 0.5
    yield from stage("before")
    result["bake"] = sorted(bake())
    messages, t0 = [], time.monotonic()
    state = bpy.context.window_manager.flowbsdf_job
    while state.running and time.monotonic() - t0 < 300:
        messages.append((round(time.monotonic() - t0, 2), round(state.progress, 1), state.message))
        if len(messages) == 8:
            yield from stage("baking")
        yield 0.25
    result["bake_messages"] = messages
    result["bake_seconds"] = round(time.monotonic() - t0, 1)
    result["after_message"] = state.message
    yield 1.0
    yield from stage("after")
    result["preview_file"] = panels.preview_file(bpy.data.materials["MilitaryGreen"])
    saved, os.environ["FLOWBSDF_PYTHON"] = os.environ.get("FLOWBSDF_PYTHON"), "/nonexistent/bin/python3.11"
    try:
        result["error_bake"] = sorted(bake())
    except RuntimeError as e:
        result["error_bake"] = str(e)
    finally:
        os.environ["FLOWBSDF_PYTHON"] = saved
    result["error_message"] = state.message
    yield from stage("error")
    yield from make_library(win, view, region, state)


def make_library(win, view, region, state):
    """Make Asset Library as an artist runs it: the button's dialog opens (its fields filled as the
    file browser would fill them: a folder of the one measured file, Draft), a screenshot of it,
    Return confirms it (the dialog's OK): the bake in the worker, then library.blend from a
    background Blender."""
    import shutil
    files = os.path.join(OUT, "measured")
    os.makedirs(files, exist_ok=True)
    if os.path.isfile(MATERIAL_FILE):
        shutil.copy(MATERIAL_FILE, files)
    ctx = {"window": win, "area": view, "region": region}
    x, y = region.x + region.width // 2, region.y + region.height // 2
    win.event_simulate(type="MOUSEMOVE", value="NOTHING", x=x, y=y)
    with bpy.context.temp_override(**ctx):
        result["library_dialog"] = sorted(bpy.ops.flowbsdf.make_library(
            "INVOKE_DEFAULT", folder=files, quality="DRAFT", out=os.path.join(OUT, "library")))
    yield 1.0
    screenshot("library_dialog")
    result["library_before_ok"] = state.running
    win.event_simulate(type="RET", value="PRESS", x=x, y=y)
    win.event_simulate(type="RET", value="RELEASE", x=x, y=y)
    yield 0.5
    result["library"] = ["RUNNING_MODAL"] if state.running else ["NOT RUNNING"]
    seen, t0 = [], time.monotonic()
    while state.running and time.monotonic() - t0 < 300:
        seen.append((state.label, round(state.progress, 1), state.message))
        yield 0.25
    result["library_messages"] = seen
    result["library_message"] = state.message


def run():
    gen = steps()

    def tick():
        try:
            return next(gen)
        except StopIteration:
            pass
        except Exception as e:      # noqa: BLE001 - reported in result.json
            import traceback
            result["errors"].append(traceback.format_exc())
            print(traceback.format_exc(), flush=True)
        with open(os.path.join(OUT, "result.json"), "w") as f:
            json.dump(result, f, indent=1)
        print("UI SCRIPT DONE", flush=True)
        bpy.ops.wm.quit_blender()
        return None
    bpy.app.timers.register(tick, first_interval=2.0)


os.makedirs(os.path.join(OUT, "project"), exist_ok=True)
run()
