"""The panel's operators. Long work runs in a worker subprocess: interactively a modal
operator polls it from a timer (Blender stays responsive, Cancel ends the job); in
background mode (batch, tests) `execute` follows it to its end. Errors are reported with
self.report, never raised as tracebacks."""
import os
import shutil

import bpy

from .. import deps
from . import jobs, prefs, props, scan, worker

USER_ERRORS = (worker.JobError, scan.ScanError, jobs.BindError, OSError, ValueError)


def _redraw(context):
    for window in getattr(context.window_manager, "windows", ()):
        for area in window.screen.areas:
            area.tag_redraw()


class _JobOperator:
    """Start a worker job, follow it (modal timer, or to the end in background), then finish().
    An error is reported as one short line (Blender's report popup is one line wide); the
    whole message goes to the panel's job box and the console."""

    def start(self, context):          # -> worker.Job (may raise a USER_ERRORS)
        raise NotImplementedError

    def finish(self, context, job):    # -> message for the info report
        return "done"

    def next_job(self, context, job):  # -> a Job that goes on with the work once `job` ended, or None
        return None

    def _next(self, context):
        """The next step's job (next_job) unless the job was cancelled; None when there is none.
        A USER_ERRORS from next_job becomes the job's error."""
        if self._job.cancelled:
            return None
        try:
            return self.next_job(context, self._job)
        except USER_ERRORS as e:
            self._job.error = str(e)
            return None

    def _fail(self, context, message, details="", cancelled=False):
        state = context.window_manager.flowbsdf_job
        state.running, state.failed = False, not cancelled
        state.message = message + (f"\n{details}" if details else "")
        _redraw(context)
        label = getattr(getattr(self, "_job", None), "label", None) or self.bl_label
        print(f"FlowBSDF {label}: {state.message}", flush=True)
        line = worker.short(message)
        more = bool(details) or line != message.strip()
        self.report({"WARNING"} if cancelled else {"ERROR"},
                    f"FlowBSDF: {line}" + (" (details in the FlowBSDF panel)" if more else ""))
        return {"CANCELLED"}

    def _start(self, context):
        self._job = None
        try:
            self._job = self.start(context)
        except USER_ERRORS as e:
            self._fail(context, str(e), getattr(e, "details", ""))
            return False
        return True

    def _end(self, context):
        job = self._job
        state = context.window_manager.flowbsdf_job
        state.running = False
        if job.error:
            return self._fail(context, f"{job.label} {'cancelled' if job.cancelled else 'failed: ' + job.error}",
                              cancelled=job.cancelled)
        try:
            message = self.finish(context, job)
        except USER_ERRORS as e:
            return self._fail(context, str(e), getattr(e, "details", ""))
        state.progress, state.message, state.failed = 100.0, message, False
        self.report({"INFO"}, message)
        return {"FINISHED"}

    def execute(self, context):
        if not self._start(context):
            return {"CANCELLED"}
        while self._job is not None:
            try:
                self._job.run(echo=bpy.app.background)
            except worker.JobError:
                pass                    # job.error holds it: reported by _end
            job, self._job = self._job, self._next(context)
        self._job = job
        return self._end(context)

    def invoke(self, context, event):
        if bpy.app.background or context.window is None:
            return self.execute(context)
        problem = jobs.unsaved_problem(context.scene)
        if problem:
            return self._fail(context, problem)
        return self._run_modal(context)

    def _run_modal(self, context):
        """Start the job and follow it from a timer (Blender stays responsive)."""
        if worker.current is not None and not worker.current.done:
            self.report({"ERROR"}, f"FlowBSDF: {worker.current.label} is still running (cancel it first)")
            return {"CANCELLED"}
        if not self._start(context):
            return {"CANCELLED"}
        worker.current = self._job
        state = context.window_manager.flowbsdf_job
        state.running, state.progress, state.message, state.label = True, 0.0, "starting", self._job.label
        state.failed = False
        self._timer = context.window_manager.event_timer_add(0.25, window=context.window)
        context.window_manager.modal_handler_add(self)
        return {"RUNNING_MODAL"}

    def modal(self, context, event):
        if event.type != "TIMER":
            return {"PASS_THROUGH"}
        job = self._job
        job.poll()
        state = context.window_manager.flowbsdf_job
        state.progress, state.message = 100.0 * job.fraction, job.message
        _redraw(context)
        if not job.done:
            return {"PASS_THROUGH"}
        nxt = self._next(context)
        if nxt is not None:             # the work's next step: followed the same way
            self._job = worker.current = nxt
            state.progress, state.message, state.label = 0.0, "starting", nxt.label
            return {"PASS_THROUGH"}
        context.window_manager.event_timer_remove(self._timer)
        result = self._end(context)
        _redraw(context)
        return result


class FLOWBSDF_OT_scan(_JobOperator, bpy.types.Operator):
    """List the learned materials that rendered objects use, what they need and what is baked;
    write them as the scene's manifest"""
    bl_idname = "flowbsdf.scan"
    bl_label = "Scan Scene"

    def start(self, context):
        self._rows, self._manifest, _, job = jobs.start_status(context.scene, context)
        return job

    def finish(self, context, job):
        statuses = jobs.after_status(context.scene, self._rows, self._manifest, job.lines)
        current = sum(scan.state_of(s) == "current" for s in statuses.values())
        return f"FlowBSDF: {len(statuses)} learned material(s), {current} baked and current; wrote {self._manifest}"


class _BakeOperator(_JobOperator):
    """Bake the tables (training first when `TRAIN` is "always") and bind the nodes."""
    TRAIN = "never"

    only_active: bpy.props.BoolProperty(name="Active material only", default=False)

    def start(self, context):
        only = None
        if self.only_active:
            mat = getattr(context, "material", None) or _active_material(context)
            if mat is None:
                raise scan.ScanError("no active material")
            only = mat.name
        self._rows, self._manifest, self._out, job = jobs.start_bake(context.scene, context, only=only,
                                                                     train=self.TRAIN)
        return job

    def finish(self, context, job):
        statuses = jobs.after_status(context.scene, self._rows, self._manifest, job.lines)
        bound = jobs.bind(self._rows, statuses)
        wrote = sum(line.startswith("[wrote] ") for line in job.lines)
        trained = sum(line.startswith("[trained] ") for line in job.lines)
        where = f" (unsaved file: tables in {self._out})" if jobs.unsaved_problem(context.scene) else ""
        return (f"FlowBSDF: {f'trained {trained} model(s), ' if trained else ''}baked {wrote} table(s), "
                f"{len(bound)} material(s) bound{where}")

    @classmethod
    def description(cls, context, properties):
        return cls.TOOLTIPS[bool(properties.only_active)]


class FLOWBSDF_OT_bake(_BakeOperator, bpy.types.Operator):
    """Bake tables and bind the Learned BSDF node, never training"""
    bl_idname = "flowbsdf.bake"
    bl_label = "Bake"
    TRAIN = "never"
    TOOLTIPS = {
        True: "Bake this material's tables and bind its node. Never trains: the tables come from the material "
              "itself, or from its trained model when From (under Tables) says so. Draft: seconds; Final: 1-4 min "
              "on 2 idle cores (measured on the ten shared measured files: about 2 min typical, 4 for the "
              "sharpest), longer on a busy machine or from a trained model",
        False: "Bake the tables of every learned material the scene renders and bind their nodes. Never "
               "trains. Draft: seconds; Final: 1-4 min per material on 2 idle cores (measured: about 2 min "
               "typical), longer on a busy machine"}


class FLOWBSDF_OT_train_bake(_BakeOperator, bpy.types.Operator):
    """Train a flow model, then bake tables and bind the Learned BSDF node"""
    bl_idname = "flowbsdf.train_bake"
    bl_label = "Train + Bake"
    TRAIN = "always"
    TOOLTIPS = {
        True: "Train a flow model for this material unless it has one (Fast: about 1 min, Balanced: 2-3 min, "
              "Paper: hours without a GPU; resumes after Cancel), then bake its tables from it (sets "
              "From: Trained model) and bind its node. Needs a Python with torch and FlowBSDF's trainer "
              "(add-on preferences)",
        False: "Train a flow model for every learned material the scene renders that has none (minutes "
               "each), then bake their tables from them and bind their nodes. Needs a Python with torch and "
               "the trainer"}

    def start(self, context):
        # Training is asked for so that the tables come from the model: say so where it is kept.
        mats = [getattr(context, "material", None) or _active_material(context)] if self.only_active \
            else [slot.material for ob in context.scene.objects for slot in ob.material_slots]
        for mat in mats:
            if mat is not None and mat.flowbsdf.enabled:
                mat.flowbsdf.tables_from = "MODEL"
        return super().start(context)


class FLOWBSDF_OT_make_library(_JobOperator, bpy.types.Operator):
    """Bake a folder of measured files (RGL .bsdf, MERL .binary) into an asset library: one material
    per file, with a preview, in a .blend that the Asset Browser opens (add its folder in
    Preferences > File Paths > Asset Libraries). The bake runs in the background like Bake; files
    already baked are skipped"""
    bl_idname = "flowbsdf.make_library"
    bl_label = "Make Asset Library"

    folder: bpy.props.StringProperty(name="Measured Files", subtype="DIR_PATH",
                                     description="The folder of measured files (subfolders too)")
    out: bpy.props.StringProperty(name="Library Folder", subtype="DIR_PATH",
                                  description="Where the library goes (library.blend, tables/, the catalogs); "
                                              "empty: a folder 'flowbsdf_library' in the measured files' folder")
    quality: bpy.props.EnumProperty(name="Tables", default="FINAL", items=props.QUALITY_ITEMS)

    def _folders(self):
        folder = bpy.path.abspath(self.folder.strip())
        if not folder or not os.path.isdir(folder):
            raise ValueError(f"pick the folder of measured files ({folder or 'none picked'} is not a folder)")
        out = bpy.path.abspath(self.out.strip()) or os.path.join(folder, "flowbsdf_library")
        return os.path.normpath(folder), os.path.normpath(out)

    def start(self, context):
        from . import library
        folder, out = self._folders()
        try:
            self._items, _, job = jobs.start_library(folder, out, self.quality.lower(), context)
        except library.LibraryError as e:
            raise ValueError(str(e)) from None
        self._failed = []
        return job

    def next_job(self, context, job):
        if job.label != "Asset Library: Bake":
            return None
        self._failed = sorted({ln.split(":", 1)[0][len("[fail] "):] for ln in job.lines if ln.startswith("[fail] ")})
        if job.error and not self._failed:
            return None                 # the bake itself failed: reported by _end
        folder, out = self._folders()
        return jobs.library_blend_job(folder, out, self.quality.lower(), context)

    def finish(self, context, job):
        _, out = self._folders()
        made = len(self._items) - len(self._failed)
        return (f"FlowBSDF: asset library {os.path.join(out, 'library.blend')}, {made} material(s)"
                + (f" ({', '.join(self._failed)} failed to bake)" if self._failed else "")
                + "; add its folder in Preferences > File Paths > Asset Libraries")

    def invoke(self, context, event):
        if bpy.app.background or context.window is None:
            return self.execute(context)
        return context.window_manager.invoke_props_dialog(self, width=420)

    def execute(self, context):
        if bpy.app.background or context.window is None:
            return super().execute(context)
        return self._run_modal(context)         # after the dialog: in the background, with the bar


class FLOWBSDF_OT_cancel(bpy.types.Operator):
    """Stop the running FlowBSDF job (training resumes from its checkpoint next time)"""
    bl_idname = "flowbsdf.cancel"
    bl_label = "Cancel"

    def execute(self, context):
        job = worker.current
        if job is None or job.done:
            self.report({"INFO"}, "FlowBSDF: nothing is running")
            return {"CANCELLED"}
        job.cancel()
        context.window_manager.flowbsdf_job.message = "cancelling"
        return {"FINISHED"}


def _active_material(context):
    obj = context.active_object
    return obj.active_material if obj is not None else None


class FLOWBSDF_OT_enable(bpy.types.Operator):
    """Make the active material a learned material (pick its source below)"""
    bl_idname = "flowbsdf.enable"
    bl_label = "Use Learned BSDF"

    def execute(self, context):
        mat = getattr(context, "material", None) or _active_material(context)
        if mat is None:
            self.report({"ERROR"}, "FlowBSDF: select an object with a material")
            return {"CANCELLED"}
        mat.flowbsdf.enabled = True
        return {"FINISHED"}


class FLOWBSDF_OT_load_model(bpy.types.Operator):
    """Use an already trained model (.flow.npz) for the active material"""
    bl_idname = "flowbsdf.load_model"
    bl_label = "Load Model"

    filepath: bpy.props.StringProperty(subtype="FILE_PATH")
    filter_glob: bpy.props.StringProperty(default="*.npz", options={"HIDDEN"})

    def invoke(self, context, event):
        context.window_manager.fileselect_add(self)
        return {"RUNNING_MODAL"}

    def execute(self, context):
        from .props import manifest_name
        mat = getattr(context, "material", None) or _active_material(context)
        src = bpy.path.abspath(self.filepath)
        if mat is None or not os.path.isfile(src) or not src.endswith(".npz"):
            self.report({"ERROR"}, f"FlowBSDF: {src or 'no file'}: pick a trained model (.flow.npz) "
                        "with a material selected")
            return {"CANCELLED"}
        dst = os.path.join(scan.out_dir(context.scene), "models", manifest_name(mat) + ".flow.npz")
        try:
            os.makedirs(os.path.dirname(dst), exist_ok=True)
            shutil.copyfile(src, dst + ".tmp")
            os.replace(dst + ".tmp", dst)
        except OSError as e:
            self.report({"ERROR"}, f"FlowBSDF: cannot copy the model to {dst}: {e}")
            return {"CANCELLED"}
        mat.flowbsdf.tables_from = "MODEL"
        self.report({"INFO"}, f"FlowBSDF: model for {mat.name} -> {dst} (From: Trained model; bake to use it)")
        return {"FINISHED"}


class FLOWBSDF_OT_check_python(bpy.types.Operator):
    """Check again what the Python that FlowBSDF's jobs use can do (bake: numpy + OpenEXR; train:
    torch + FlowBSDF's trainer)"""
    bl_idname = "flowbsdf.check_python"
    bl_label = "Check Python"

    def execute(self, context):
        deps.clear_probes()
        p = prefs.get(context)
        text, icon = deps.summary(p.python_path if p else "", worker.extra_paths(p))[-1]
        print(f"FlowBSDF: {text}", flush=True)
        self.report({"ERROR"} if icon == "ERROR" else {"INFO"}, f"FlowBSDF: {worker.short(text, 160)}")
        return {"FINISHED"} if icon != "ERROR" else {"CANCELLED"}


class FLOWBSDF_OT_set_backend(bpy.types.Operator):
    """Choose how Learned BSDF nodes render: OSL (exact sampling, CPU) or the closure fit (everywhere)"""
    bl_idname = "flowbsdf.set_backend"
    bl_label = "Set Back End"

    backend: bpy.props.EnumProperty(items=[("osl", "OSL", ""), ("svm", "SVM graph", ""), ("fit", "Closure fit", ""),
                                           ("auto", "Auto", "")])

    def execute(self, context):
        try:
            from ..render import node
            node.set_backend(context.scene, self.backend)
        except (ImportError, ValueError, RuntimeError) as e:
            self.report({"ERROR"}, f"FlowBSDF: {e}")
            return {"CANCELLED"}
        return {"FINISHED"}


class FLOWBSDF_OT_use_osl(bpy.types.Operator):
    """Render with Cycles on the CPU with Open Shading Language on (Render Properties): the Learned
    BSDF's exact back end with the least noise, lamps included"""
    bl_idname = "flowbsdf.use_osl"
    bl_label = "Turn On OSL (CPU)"
    bl_options = {"UNDO"}

    def execute(self, context):
        scene = context.scene
        scene.render.engine = 'CYCLES'
        scene.cycles.device = 'CPU'
        scene.cycles.shading_system = True
        return {"FINISHED"}


class FLOWBSDF_OT_use_cycles(bpy.types.Operator):
    """Render with Cycles, where the Learned BSDF renders its baked tables (EEVEE renders its fit)"""
    bl_idname = "flowbsdf.use_cycles"
    bl_label = "Render with Cycles"
    bl_options = {"UNDO"}

    def execute(self, context):
        context.scene.render.engine = 'CYCLES'
        return {"FINISHED"}


class FLOWBSDF_OT_reach_lamp(bpy.types.Operator):
    """Let the SVM back end reach this lamp: visible to the camera, with a size (Radius 0.1 m, a
    sun's Angle 0.53 deg, Blender's defaults) and Multiple Importance on"""
    bl_idname = "flowbsdf.reach_lamp"
    bl_label = "Let the SVM Back End Reach the Lamp"
    bl_options = {"UNDO"}

    lamp: bpy.props.StringProperty()

    def execute(self, context):
        from ..render import lamps
        ob = context.scene.objects.get(self.lamp)
        if ob is None or ob.type != 'LIGHT':
            self.report({"ERROR"}, f"FlowBSDF: no lamp {self.lamp!r} in the scene")
            return {"CANCELLED"}
        lamps.reach(ob)
        return {"FINISHED"}


classes = (FLOWBSDF_OT_scan, FLOWBSDF_OT_bake, FLOWBSDF_OT_train_bake, FLOWBSDF_OT_make_library, FLOWBSDF_OT_cancel,
           FLOWBSDF_OT_enable,
           FLOWBSDF_OT_load_model, FLOWBSDF_OT_check_python, FLOWBSDF_OT_set_backend, FLOWBSDF_OT_use_osl,
           FLOWBSDF_OT_use_cycles, FLOWBSDF_OT_reach_lamp)
