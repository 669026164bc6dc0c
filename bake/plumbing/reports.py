"""`flowbsdf report` and the main job's report stage: a manifest entry's trained flow and current
tables, found in an output folder, measured beside the baselines by bake/quality/report.py."""
from pathlib import Path

from ..io.paths import model_path, table_path
from ..quality.report import THETAS_DEG, entry_report, write_report
from .pipeline import StaleTables, open_baked


def learned_samplers(entry, material, out_dir, manifest_path, log=print):
    """(flow, tables): the entry's trained flow and its current baked tables under `out_dir`, each
    None where there is none (stale tables are left out, saying so)."""
    flow = open_baked("flow", entry, material, out_dir) if model_path(out_dir, entry.name).is_file() else None
    tables = None
    if table_path(out_dir, entry.name).is_file():
        try:
            tables = open_baked("tables", entry, material, out_dir, manifest_path)
        except StaleTables:
            log(f"[report] {entry.name}: tables are stale (material, model or settings changed): re-bake")
    return flow, tables


def report_manifest(manifest, out_dir, name=None, thetas=THETAS_DEG, n=1 << 17, steps=(2, 4, 8), log=print):
    """The speed-vs-error report of every selected material, written to <out_dir>/report."""
    rows, slices = [], []
    for entry in manifest.select(name, log=log):
        material = entry.open()
        flow, tables = learned_samplers(entry, material, out_dir, manifest.path, log)
        entry_rows, entry_slice = entry_report(entry, material, flow, tables, thetas, n, steps, log)
        rows += entry_rows
        slices.append(entry_slice)
    return write_report(rows, Path(out_dir) / "report", slices=slices)
