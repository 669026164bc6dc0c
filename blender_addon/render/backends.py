"""Which back end a Learned BSDF node renders in a scene, and why, in the words of Blender's UI:
the scene's setting ("auto", "osl", "svm", "fit"; `backend_of`), what each back end needs (OSL:
Cycles on the CPU with OSL on; the SVM graph: lamps it can reach, enough samples) and the one step
to an exact back end (`resolve` -> Status)."""
import os
from typing import NamedTuple

import bpy

from . import binding, lamps, osl_script

BACKENDS = ("osl", "svm", "fit", "auto")
ENUM_ORDER = ("auto", "osl", "fit", "svm")     # the scene enum's items, as stored in files (append only)
SCENE_PROP = "flowbsdf_backend"


def backend_of(scene):
    """The scene's back end setting: "osl", "fit" or "auto" (default)."""
    if hasattr(bpy.types.Scene, SCENE_PROP):
        value = getattr(scene, SCENE_PROP)
    else:
        value = scene.get(SCENE_PROP)
        if isinstance(value, int):        # the enum as stored by a session with the add-on
            value = ENUM_ORDER[value] if 0 <= value < len(ENUM_ORDER) else "auto"
    return value if value in BACKENDS else "auto"


def osl_available(scene):
    """(bool, why not, in the UI's words): OSL renders in this scene's settings."""
    if scene.render.engine != 'CYCLES':
        return False, f"{engine_name(scene)} runs no OSL"
    if scene.cycles.device != 'CPU':
        return False, "OSL needs the CPU"
    if not scene.cycles.shading_system:
        return False, "OSL is off"
    return True, ""


ENGINE_NAMES = {"BLENDER_EEVEE": "EEVEE", "BLENDER_EEVEE_NEXT": "EEVEE", "BLENDER_WORKBENCH": "Workbench",
                "CYCLES": "Cycles"}


def engine_name(scene):
    return ENGINE_NAMES.get(scene.render.engine, scene.render.engine.title())


class Status(NamedTuple):
    """What a Learned BSDF node renders in a scene, in the words of Blender's UI: `text` what
    renders and how far it is from the measured material, `action` the one step that gets the
    exact material in this scene ("" where it renders exactly), `operator` the button that takes
    the step, (bl_idname, {property: value}), or () where the artist takes it, and `detail` what
    the short words leave out (a path, a wait, a clamp): the panel's last lines and the logs."""
    backend: str            # what renders: "osl", "svm" or "fit"
    text: str
    action: str = ""
    operator: tuple = ()
    detail: str = ""

    def line(self):
        """The status as one line (logs, reports, node_status)."""
        return (self.text + (f". {self.action}" if self.action else "")
                + (f" ({self.detail})" if self.detail else ""))


USE_OSL = ("Turn On OSL (CPU)", ("flowbsdf.use_osl", {}))
USE_SVM = ("Set Back End to SVM", ("flowbsdf.set_backend", {"backend": "svm"}))
BAKE = ("Bake the Material", ("flowbsdf.bake", {"only_active": True}))


def _reach(hidden):
    """(why, step) for the first lamp of `hidden` (lamps.unreachable): what keeps the SVM
    back end's portal from it and the button that makes it reachable."""
    name, why = next(iter(hidden.items()))
    text, button = lamps.REACH[why]
    return text.format(name), (button, ("flowbsdf.reach_lamp", {"lamp": name}))


# Render samples from which `auto` takes the SVM graph under lamps it reaches (not OSL's): at
# equal CPU time to Principled's 4096 spp (Blender's default; the SVM graph gets ~800) its MSE
# against the measured file is below the fit's (studio lamps, 48 px sphere, 6 seeds, hashed u
# as under Blender's default pixel filter; the FIT_VERSION 7 fit: SVM / fit 0.13 / 0.72 / 0.58 on
# colodur_napoli_4f, cc_nothern_aurora, irid_flake_paint1, files the lamp work was not tuned on;
# 0.80 / 0.47 / 1.73 on cm_military_green, vch_golden_yellow, satin_rosaline); at 128 spp 4-19x.
# Measured without adaptive sampling (tests/cycles_scenes.reset): with it, svm_pays.
SVM_LAMP_SAMPLES = 4096


def svm_pays(scene):
    """Whether the scene's render samples reach SVM_LAMP_SAMPLES (the SVM graph beats the fit
    under lamps at equal time from about there) with adaptive sampling off, in Blender 5.0+ where
    that was measured (4.5's SVM graph, Transparent Depth for Portal Depth, is 4-6x noisier under
    lamps relative to OSL: tests/test_cycles_lights.py's unbiased test, 62/22/19x OSL's variance
    against 5.0's 15/12/11x). Adaptive sampling (Blender's default Noise Threshold 0.01) stops the
    fit's pixels early and the SVM graph's late: at Blender's render settings (denoising off;
    studio lamps, 48 px, 2 seeds, MSE against the file) both at 4096 samples, SVM / fit MSE 1.16
    (cm_military_green) and 0.21 (vch_golden_yellow) at 3.5x and 6.8x the fit's CPU time: at
    equal time the fit wins (~4x and ~1.9x) (the note of s41, svmdef). With denoising on too
    (Blender's default; scripts/denoise_pays.py, 96 px, 3 seeds, session 47) the fit still wins at
    equal time: SVM at 64-4096 samples cost 1.4-19x the fit's CPU at 4096, and the denoiser makes
    the SVM graph's image worse, not better (vch_golden_yellow, 1024 samples: MSE 4.8e-4 undenoised,
    3.1-3.2e-3 denoised, 4.9e-3 with the denoiser's albedo/normal guides off; the fit's whole MSE
    7.5e-4, its bias); cm_military_green's SVM at 64 samples, denoised, 1.6x the fit's MSE at 1.4x
    its CPU."""
    return (bpy.app.version >= (5, 0, 0) and int(scene.cycles.samples) >= SVM_LAMP_SAMPLES
            and not scene.cycles.use_adaptive_sampling)


def clamp_note(scene):
    """What the scene's clamping does to the SVM graph under lamps ("" without clamping): Cycles
    clamps each path's contribution, and the light the graph's portal carries arrives in fewer,
    larger contributions than the OSL shader's next-event estimation (its portal finds the lamps),
    so a clamp takes more of it. Measured at Blender's render settings (Clamp Indirect 10), a
    Diffuse wall lit only by a learned sphere (satin_rosaline) under an area lamp: the wall's mean
    -5.0 % with SVM, -1.1 % with OSL (SE 0.8 %); a sphere on a Diffuse floor under the studio
    lamps (cm_military_green): no change (tests/test_cycles_lights.py's wall, the note of s41)."""
    cy = scene.cycles
    limits = [(name, float(getattr(cy, prop, 0.0))) for name, prop in
              (("Clamp Direct", "sample_clamp_direct"), ("Clamp Indirect", "sample_clamp_indirect"))]
    on = [f"{name} {v:g}" for name, v in limits if v > 0.0]
    if not on:
        return ""
    return f"{' and '.join(on)} clamp the light its portal carries more than OSL's (measured to -5 %)"


def caustics_off(scene):
    """Whether the scene turns Caustics (reflective or refractive) off."""
    cy = getattr(scene, "cycles", None)
    return cy is not None and not (cy.caustics_reflective and cy.caustics_refractive)


# What the OSL back end costs before the first pixel where Cycles keeps nothing between renders:
# it compiles each material's shader at every render. Measured (scripts/osl_first_pixel.py, bpy
# 5.0.1, 2 cores, process CPU per Learned BSDF material, draft tables of cm_military_green, best of
# 2 at load 7-14): 1.9-2.1 s without lamps, 2.6-2.9 s with 1 or 8 lamps; with the carried blend
# 4.0-5.2 s (a Principled BSDF 0.05 s). Seconds by (carried blend):
COMPILE_SECONDS = {False: "2-3", True: "4-5"}


def compile_note(scene, carried=False):
    """The OSL back end's wait before the first pixel, in the artist's words ("" where Persistent
    Data keeps the compiled shader between renders)."""
    if getattr(scene.render, "use_persistent_data", False):
        return ""
    return (f"every render first compiles the shader, ~{COMPILE_SECONDS[carried]} s per material before the first "
            "pixel; Render Properties > Performance > Persistent Data compiles it once")


def resolve(scene, tree, limits=None):
    """The Status of one group in one scene (`limits`: lamps.limits(scene), computed here when
    not given). The exact back ends by preference: OSL (CPU; lamps by next-event estimation in
    the shader: the least noise), then the SVM graph (every device), else the fit."""
    info = binding.read(tree)
    backend = backend_of(scene)
    if info.get("has_fit"):
        err, of = info.get("fit_error", -1.0), "measured material" if info.get("fit_error_of") == "file" else "tables"
        if scene.render.engine != 'CYCLES':        # EEVEE's own fit
            err = info.get("eevee_error", -1.0)
        fit = f"Fit, ~{100 * err:.0f} % off the {of}" if err >= 0 else "Fit"
    else:
        fit = "Neutral grey (no fit)"

    def fallback(why, step, detail=""):
        return Status("fit", f"{fit} ({why})", step[0], step[1], detail)
    if backend == "fit":
        return fallback("Back End: Fit", ("Set Back End to Auto", ("flowbsdf.set_backend", {"backend": "auto"})))
    if scene.render.engine != 'CYCLES':
        return fallback(engine_name(scene), ("Render with Cycles", ("flowbsdf.use_cycles", {})))
    tables = info.get("tables", "")
    if not tables or not os.path.isfile(tables):
        return fallback("tables missing", BAKE, f"tables missing: {tables}")
    osl_ok, osl_why = osl_available(scene)
    osl_step = USE_OSL
    if tree.nodes.get(osl_script.SCRIPT) is None:          # built in a Blender that cannot compile OSL
        osl_ok, osl_why, osl_step = False, "no OSL in this Blender", None
    elif not os.path.isfile(info.get("osl_texture", "")):
        osl_ok, osl_why, osl_step = False, "OSL texture missing", BAKE
    svm_ok = binding.has_svm(tree) and os.path.isfile(info.get("svm_texture", ""))
    notes = lamps.limits(scene) if limits is None else limits
    if osl_ok and backend in ("osl", "auto"):
        carried = os.path.isfile(info.get("carry_texture", ""))
        exact = "OSL, carried blend, exact" if carried else "OSL, exact"
        wait = compile_note(scene, carried)
        if notes:
            return Status("osl", f"{exact}, but {notes[0][0]}", notes[0][1], (),
                          "; ".join([n for n, _ in notes] + ([wait] if wait else [])))
        return Status("osl", exact, detail=wait)
    lit = lamps.scene_lamps(scene)
    # The SVM graph lights its fit's closures by Cycles' lamp sampling and the rest through its
    # portal, which draws toward the lamps visible to the camera that have a size: exact there.
    # Its error is noise, the fit's bias: at equal CPU time (studio lamps, 48 px sphere, MSE
    # against the FILE, scripts/lights_acceptance.py) the fit wins at Principled's 128 spp (SVM
    # 9-19x its MSE) and SVM at Blender's default 4096 (SVM_LAMP_SAMPLES) without adaptive
    # sampling (with it the fit: svm_pays), `auto` follows.
    hidden = lamps.unreachable(scene) if lit else {}
    if svm_ok and (backend == "svm" or not lit or (backend == "auto" and not hidden and svm_pays(scene))):
        clamped = "; ".join(n for n in ((clamp_note(scene) if lit else ""),
                                        ("Caustics off: control variate off" if lit and caustics_off(scene) else "")) if n)
        if hidden:
            why, step = _reach(hidden)
            return Status("svm", f"SVM, exact but {why}: it lights only the fit", *step,
                          detail="; ".join([f"{n}: {w}" for n, w in hidden.items()] + ([clamped] if clamped else [])))
        return Status("svm", "SVM, exact", detail=clamped)
    # The fit renders: the step to an exact back end. OSL where the node has it, on the CPU;
    # where the scene renders on the GPU, the SVM graph (every device runs it) first.
    if backend == "svm":
        why = "no SVM in this Blender"
    else:
        why = "lamps need OSL" if lit and backend == "auto" and osl_step is USE_OSL else osl_why
    if svm_ok and (scene.cycles.device != 'CPU' or osl_step is None):
        if hidden:
            why, step = _reach(hidden)
        else:
            why, step = (why if not lit else f"under lamps SVM needs {SVM_LAMP_SAMPLES}+ samples"
                         if int(scene.cycles.samples) < SVM_LAMP_SAMPLES else "under lamps SVM needs Noise Threshold off"), USE_SVM
        return fallback(why, step)
    return fallback(why, osl_step or ("Render in Blender 5.0+", ()))
