// FlowBSDF Bake: a Flamenco (3.x) custom job type.
//
// Per learned material, a `train-NAME` task (exec: `flowbsdf farm task ... --stage train`, on a
// worker whose Python has torch) and a `bake-NAME` task that depends on it (`--stage bake`);
// then one `assemble` task after every bake (blender-render: the add-on's batch command binds
// each material's node to its tables and saves the .blend). With train = never there are no
// train tasks. Install: copy this file into the Manager's `scripts/` folder and restart it.
// Settings, worker set-up and what was run: docs/farm.md. Task logic lives in bake/plumbing/farm.py.

const JOB_TYPE = {
    label: "FlowBSDF Bake",
    description: "Train (where needed) and bake each learned material's tables, then bind and save the .blend",
    settings: [
        { key: "materials", type: "string", required: true,
          eval: "','.join(m['name'] for m in __import__('tomllib').loads(open(bpy.path.abspath(" +
                "(C.scene.flowbsdf.out_dir.strip() or '//flowbsdf') + '/manifest.toml'), " +
                "encoding='utf-8').read())['material'])",
          description: "Comma-separated manifest names (read from the scene's manifest: Scan Scene writes it)" },
        { key: "manifest", type: "string", subtype: "file_path", required: true,
          eval: "bpy.path.abspath((C.scene.flowbsdf.out_dir.strip() or '//flowbsdf') + '/manifest.toml')",
          description: "The scene's FlowBSDF manifest, on shared storage" },
        { key: "shared_out", type: "string", subtype: "dir_path", required: true,
          eval: "bpy.path.abspath(C.scene.flowbsdf.out_dir.strip() or '//flowbsdf')",
          description: "Shared output folder: models/ and tables/" },
        { key: "train", type: "string", choices: ["auto", "always", "never"], default: "auto",
          description: "auto: train where the manifest wants a model and the worker's Python has torch" },
        { key: "python", type: "string", default: "{flowbsdf_python}",
          description: "The workers' Python with FlowBSDF (a Manager variable per platform)" },
        { key: "train_task_type", type: "string", default: "misc",
          description: "Task type of the train tasks: give torch workers their own type to route training there" },
        { key: "assemble", type: "bool", default: true,
          description: "After the bakes, bind the nodes and save the .blend (save_as)" },
        { key: "save_as", type: "string", subtype: "file_path", required: true,
          eval: "__import__('os').path.splitext(bpy.data.filepath)[0] + '.flowbsdf.blend'",
          description: "Where the assemble task saves the bound .blend" },
        { key: "addon_dir", type: "string", subtype: "dir_path", default: "",
          description: "Folder holding the `flowbsdf` add-on on the workers (empty: the installed one)" },
        { key: "blendfile", type: "string", required: true, visible: false,
          description: "The .blend (set by Flamenco's add-on)" },
    ],
};

function compileJob(job) {
    const settings = job.settings;
    const names = settings.materials.split(",").map((n) => n.trim()).filter((n) => n.length > 0);
    if (names.length == 0) {
        throw "FlowBSDF: no materials to bake (the 'materials' setting is empty: scan the scene first)";
    }
    const bakes = [];
    for (const name of names) {
        const bake = materialTask(settings, name, "bake", "misc");
        if (settings.train != "never") {
            const train = materialTask(settings, name, "train", settings.train_task_type);
            job.addTask(train);
            bake.addDependency(train);
        }
        job.addTask(bake);
        bakes.push(bake);
    }
    if (settings.assemble) {
        const assemble = author.Task("assemble", "blender");
        assemble.addCommand(author.Command("blender-render", {
            exe: "{blender}",
            exeArgs: "{blenderArgs}",
            argsBefore: [],
            blendfile: settings.blendfile,
            args: ["--python-expr", batchExpr(settings.addon_dir), "--", "bake", "--train", "never",
                   "--out", settings.shared_out, "--python", settings.python, "--save-as", settings.save_as],
        }));
        for (const bake of bakes) {
            assemble.addDependency(bake);
        }
        job.addTask(assemble);
    }
}

// One material's stage: `python -m bake.plumbing.cli farm task` (bake/plumbing/farm.py).
function materialTask(settings, name, stage, taskType) {
    const task = author.Task(`${stage}-${name}`, taskType);
    task.addCommand(author.Command("exec", {
        exe: settings.python,
        args: ["-m", "bake.plumbing.cli", "farm", "task", settings.manifest, "--material", name,
               "--out", settings.shared_out, "--train", settings.train, "--stage", stage],
    }));
    return task;
}

// The add-on's batch entry for Blender 3.4+ (bake/plumbing/farm.py blender_expr: the same text).
function batchExpr(addonDir) {
    return `import sys; d = r'''${addonDir || ""}'''; d and sys.path.insert(0, d); ` +
           "import flowbsdf.batch as b; b.main()";
}
