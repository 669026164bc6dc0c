"""BakeSettings: a manifest's `[bake]` table (bake/plumbing/manifest.py), checked once, as the
planner takes it (planner.plan_tables).

Each setting is declared once below: its default (the planner's) and, for the numeric ones, its
limits: (type, low, high), a typo like resolution = 1e9 must be an error, not a bake that asks for
terabytes. `BakeSettings.from_table` refuses an unknown key or a bad value with the words users
see (tests/test_bad_inputs.py, test_manifest.py).

`given` names the keys the table set: a table file records its settings as given (`inputs`, with
source and carry always), so that tables baked before this class still hash alike and stay current.
"""
from dataclasses import dataclass, field, fields

from ..errors import FlowBSDFError

SOURCES = ("auto", "flow", "ideal")


def _limits(kind, lo, hi, default, word=None):
    """A numeric setting's field: its default and limits (`word`: a string also allowed, e.g. "auto")."""
    return field(default=default, metadata={"limits": (kind, lo, hi), "word": word})


@dataclass(frozen=True)
class BakeSettings:
    # Where the cells' placement comes from: "auto" and "ideal" the ideal tabulation, "flow" the
    # material's trained model (pipeline.tables_use_model).
    source: str = "auto"
    # The carried blend is opt-in (`carry = true`): at equal render time it lost to the fixed cells
    # against the measured file, 6.4-7.1x the MSE (studio lamps) and 10.0-10.5x (HDRI), OSL on
    # cm_military_green, vch_golden_yellow, satin_rosaline at the default bake (it costs 5-6x the
    # time per sample; scripts/lights_acceptance.py --reference file), and only OSL renders it
    # (the SVM graph blends at fixed cells: two looks of one material). Stated in the settings,
    # so tables baked before under the old default are out of date (and baked again) once.
    carry: bool = False
    tol: float = _limits(float, 0.0, 10.0, None)        # None: planner.ISO_TOL / ANISO_TOL
    ideal_ratio: float = _limits(float, 0.0, 1000.0, 1.0)
    memory_budget: int = _limits(int, 1 << 10, 1 << 34, 4_000_000)
    resolution: int = _limits(int, 2, 1024, None)       # None: planned (planner.RESOLUTIONS)
    grid: int = _limits(int, 8, 4096, 512)
    lobe_width: float = _limits(float, 0.0, 1.6, "auto", word="auto")
    samples: int = _limits(int, 64, 1 << 24, 1 << 14)
    first_bins: int = _limits(int, 2, 512, 6)
    ideal_resolution: int = _limits(int, 8, 2048, 256)
    phi_count: int = _limits(int, 1, 256, "auto")       # "auto": planned (planner.PHI_COUNTS)
    given: tuple = field(default=(), compare=False)

    @classmethod
    def from_table(cls, table, where="", path=None):
        """The settings of a `[bake]` table; FlowBSDFError naming `where` (e.g. "material 'x'")
        and the manifest `path` for an unknown key or a value out of its limits."""
        table = dict(table)
        prefix = f"{where}: " if where else ""
        keys = {f.name for f in fields(cls)} - {"given"}
        unknown = sorted(set(table) - keys)
        if unknown:
            raise FlowBSDFError(f"{prefix}unknown bake setting(s) {', '.join(unknown)} "
                                f"(allowed: {', '.join(sorted(keys))})", path)
        if table.get("source", "auto") not in SOURCES:
            raise FlowBSDFError(f"{prefix}bake source must be one of {SOURCES}", path)
        if not isinstance(table.get("carry", False), bool):
            raise FlowBSDFError(f"{prefix}bake setting carry = {table['carry']!r} is not true or false", path)
        declared = {f.name: f for f in fields(cls)}
        for key, value in table.items():
            problem = _problem(declared[key], value)
            if problem:
                raise FlowBSDFError(f"{prefix}bake setting {key} = {value!r} {problem}", path)
        return cls(**table, given=tuple(table))

    def inputs(self):
        """The settings as a table file records them (pipeline.inputs_of): the keys given, and the
        source and carry always."""
        return {**{key: getattr(self, key) for key in self.given}, "source": self.source, "carry": self.carry}


def _problem(spec, value):
    """Why a value is unusable for the setting `spec` (a dataclass field), or None."""
    if "limits" not in spec.metadata or (spec.metadata["word"] is not None and value == spec.metadata["word"]):
        return None
    kind, lo, hi = spec.metadata["limits"]
    ok_type = isinstance(value, int) if kind is int else isinstance(value, (int, float))
    if isinstance(value, bool) or not ok_type:
        return f"must be {'an integer' if kind is int else 'a number'}"
    if not (lo < value <= hi if kind is float else lo <= value <= hi):
        return f"is out of range ({'(' if kind is float else '['}{lo}, {hi}])"
    return None
