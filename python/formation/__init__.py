"""Distributed leader-follower formation control from Python.

The simulator, scenarios and run folders of the ``formation`` project
(bioinspired backstepping and sliding-mode control, a distributed leader
estimator and the adaptive sliding innovation filter), compiled from the
same Rust code as the ``formation`` command line: a run here is the run
``formation sim`` writes, bit for bit. See docs/python.md.

>>> import formation
>>> s = formation.Scenario.load("paper")
>>> s["filter"] = "kf"
>>> run = formation.sim(s)
>>> run.followers[1]["formation_error"][-1]          # a float64 numpy array
"""

from __future__ import annotations

import json
import math
import os
from typing import Any, Dict, Iterator, List, Mapping, Optional, Sequence, Union

import numpy as np

from . import _formation

__all__ = ["Scenario", "Run", "Table", "PaperTable", "Claim", "Paper", "sim", "read_run", "generate", "paper", "replay", "BUILT_IN"]

#: The scenarios built into the package (and the command line), by name.
BUILT_IN = ("paper", "paper-velocity", "paper-tables", "turtlebot", "swap", "rotation", "doorway", "teleop")

PathLike = Union[str, "os.PathLike[str]"]


def _literal(value: Any) -> str:
    """A Python value as the VALUE of a ``--set KEY=VALUE``."""
    if isinstance(value, str):
        # As on the command line: a bare name (``kf``) or TOML text
        # (``{node=3, from=8, to=11}``).
        return value
    if isinstance(value, (bool, np.bool_)):
        return "true" if value else "false"
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    if isinstance(value, (float, np.floating)):
        v = float(value)
        if math.isnan(v):
            return "nan"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return repr(v)
    if isinstance(value, Mapping):
        items = ", ".join(f"{k} = {_toml_value(v)}" for k, v in value.items())
        return "{" + items + "}"
    if isinstance(value, (list, tuple, np.ndarray)):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    raise TypeError(f"cannot set a {type(value).__name__} as a scenario value")


def _toml_value(value: Any) -> str:
    if isinstance(value, str):
        return json.dumps(value)  # a basic TOML string
    return _literal(value)


class Scenario:
    """A scenario: load one, read and change its keys, run it, save it.

    Keys are named as ``--set`` names them (``robot.mass``,
    ``followers[0].offset``, ``faults`` …; every key: docs/scenarios.md), and
    every change goes through ``--set``'s checks: a bad value raises
    ``ValueError`` with the command line's message, and leaves the scenario
    as it was.
    """

    __slots__ = ("_raw",)

    def __init__(self, raw: "_formation.RawScenario"):
        self._raw = raw

    @classmethod
    def load(cls, path_or_name: PathLike = "paper", **sets: Any) -> "Scenario":
        """A scenario file, or a built-in one by name (see ``BUILT_IN``).

        Keyword arguments are assignments: ``Scenario.load("paper",
        duration=5)``; a dotted key goes through :meth:`set`.
        """
        s = cls(_formation.RawScenario.load(os.fspath(path_or_name)))
        for key, value in sets.items():
            s[key] = value
        return s

    @classmethod
    def from_toml(cls, text: str, name: str = "scenario") -> "Scenario":
        """A scenario from TOML text; ``name`` is its run name if it gives none."""
        return cls(_formation.RawScenario.from_toml(text, name))

    def set(self, assignment: str) -> "Scenario":
        """Applies ``KEY=VALUE`` exactly as ``--set KEY=VALUE`` does
        (``faults+={node=3, from=8, to=11}`` appends a row). Returns self."""
        self._raw.set(assignment)
        return self

    def __setitem__(self, key: str, value: Any) -> None:
        self._raw.set(f"{key}={_literal(value)}")

    def __getitem__(self, key: str) -> Any:
        value = self._raw.get(key)
        if value is None:
            raise KeyError(key)
        return value

    def get(self, key: str, default: Any = None) -> Any:
        value = self._raw.get(key)
        return default if value is None else value

    def __contains__(self, key: str) -> bool:
        return self._raw.get(key) is not None

    def copy(self) -> "Scenario":
        """An independent copy (changes to it leave this one alone)."""
        return Scenario(self._raw.copy())

    def with_(self, **sets: Any) -> "Scenario":
        """A copy with keys changed: ``s.with_(filter="kf")``. A dotted key
        cannot be a keyword: use ``s.copy().set("robot.mass=12")``."""
        c = self.copy()
        for key, value in sets.items():
            c[key] = value
        return c

    def to_dict(self) -> Dict[str, Any]:
        """Every key as it runs (defaults filled in), as nested dicts."""
        return self._raw.to_dict()

    def to_toml(self) -> str:
        """The scenario as a TOML file, every key written out."""
        return self._raw.to_toml()

    def save(self, path: PathLike) -> None:
        """Writes :meth:`to_toml` to ``path`` (``formation sim path`` runs it)."""
        with open(path, "w", encoding="utf-8") as f:
            f.write(self.to_toml())

    @property
    def name(self) -> str:
        return self._raw.name

    @property
    def overrides(self) -> List[str]:
        """The assignments made so far, as ``--set`` arguments."""
        return list(self._raw.overrides)

    @property
    def follower_ids(self) -> List[int]:
        return list(self._raw.follower_ids)

    @property
    def steps(self) -> int:
        """Steps T/Δt; a run has ``steps + 1`` samples."""
        return self._raw.steps

    @property
    def dt(self) -> float:
        return self._raw.dt

    @property
    def warning(self) -> Optional[str]:
        """The estimator's stability warning, where the gains call for one."""
        return self._raw.warning

    def __repr__(self) -> str:
        sets = "".join(f", --set {a}" for a in self._raw.overrides)
        return (
            f"<Scenario {self.name!r} ({self._raw.label}{sets}): {len(self.follower_ids)} followers, "
            f"{self.steps} steps of {self.dt} s>"
        )


class Table(Mapping[str, np.ndarray]):
    """One CSV of a run as named float64 columns (numpy arrays)."""

    __slots__ = ("_columns",)

    def __init__(self, columns: Dict[str, np.ndarray]):
        self._columns = columns

    def __getitem__(self, name: str) -> np.ndarray:
        return self._columns[name]

    def __iter__(self) -> Iterator[str]:
        return iter(self._columns)

    def __len__(self) -> int:
        return len(self._columns)

    @property
    def columns(self) -> List[str]:
        return list(self._columns)

    @property
    def rows(self) -> int:
        first = next(iter(self._columns.values()), None)
        return 0 if first is None else len(first)

    def to_numpy(self) -> np.ndarray:
        """A (rows, columns) float64 array, in the CSV's column order (a copy)."""
        return np.column_stack(list(self._columns.values())) if self._columns else np.empty((0, 0))

    def to_pandas(self):
        """A pandas DataFrame (pandas must be installed)."""
        import pandas as pd

        return pd.DataFrame(self._columns, copy=False)

    def to_polars(self):
        """A polars DataFrame (polars must be installed)."""
        import polars as pl

        return pl.DataFrame(self._columns)

    def __repr__(self) -> str:
        return f"<Table {self.rows} rows × {len(self)} columns: {', '.join(self._columns)}>"


class Run:
    """A run, simulated (:func:`sim`) or read from its folder (:func:`read_run`).

    ``followers[id]`` and ``leader`` are :class:`Table` s of the CSVs'
    columns; ``summary`` is summary.json as a dict; ``faults`` the fault
    table's figures; ``network`` network.json where the run was networked.
    """

    __slots__ = ("followers", "leader", "summary", "network", "error", "path", "problems")

    def __init__(self, raw: Dict[str, Any], path: Optional[str] = None):
        self.followers: Dict[int, Table] = {int(i): Table(c) for i, c in raw["followers"].items()}
        self.leader: Table = Table(raw["leader"])
        self.summary: Dict[str, Any] = json.loads(raw["summary"])
        network = raw.get("network")
        self.network: Optional[Dict[str, Any]] = json.loads(network) if network else None
        #: Why the run stopped early (its arrays then end there), or None.
        self.error: Optional[str] = raw.get("error")
        self.path = path
        #: A replay's steps it could not re-compute, one line each (:func:`replay`).
        self.problems: List[str] = list(raw.get("problems") or [])

    @property
    def complete(self) -> bool:
        return bool(self.summary.get("complete", True)) and self.error is None

    @property
    def faults(self) -> List[Dict[str, Any]]:
        """The fault table's figures (summary.json's ``faults``)."""
        return list(self.summary.get("faults") or [])

    def metrics(self, name: str) -> Dict[int, Any]:
        """One summary figure per follower: ``run.metrics("formation_rms_last10")``."""
        return {int(i): f.get(name) for i, f in self.summary.get("followers", {}).items()}

    def __repr__(self) -> str:
        where = f" from {self.path}" if self.path else ""
        state = "complete" if self.complete else f"incomplete ({self.error or 'see summary'})"
        rows = self.leader.rows
        return f"<Run {self.summary.get('scenario')!r}{where}: {len(self.followers)} followers, {rows} rows, {state}>"


def sim(
    scenario: Union[Scenario, PathLike] = "paper", threads: int = 1, every: int = 1, columns: bool = True
) -> Run:
    """Runs a scenario in process and returns the run in memory.

    The numbers are ``formation sim``'s CSVs and summary.json, bit for bit.
    ``threads``: the followers of each step on that many threads (the
    numbers do not change); ``every``: keep every N-th sample (and the last),
    as ``--every``; ``columns=False``: the summary only, as ``--no-csv``
    (the fastest, for sweeps). The GIL is released while it runs: Python
    threads run several scenarios on every core.
    """
    if not isinstance(scenario, Scenario):
        scenario = Scenario.load(scenario)
    if threads < 1:
        raise ValueError(f"threads must be at least 1, not {threads}")
    if every < 1:
        raise ValueError(f"every must be at least 1, not {every}")
    return Run(_formation.sim(scenario._raw, threads, every if columns else None))


def read_run(path: PathLike) -> Run:
    """Reads any run folder (``formation sim``'s or a networked run's)."""
    p = os.fspath(path)
    return Run(_formation.read_run(p), path=p)


def replay(path: PathLike, hearing: str = "recorded") -> Run:
    """A networked run re-computed in process from its folder, as
    ``formation replay`` does: with ``hearing="recorded"`` from what each
    follower heard (``hearing.bin``; equal to the run byte for byte where
    nothing was lost), with ``"model"`` from what the model says it would
    have heard (the run the simulator predicts). ``run.problems`` names
    the steps it could not re-compute."""
    if hearing not in ("recorded", "model"):
        raise ValueError(f"hearing {hearing!r}: recorded or model")
    p = os.fspath(path)
    return Run(_formation.replay(p, hearing == "model"), path=p)


def generate(
    followers: int,
    graph: str = "ring",
    chords: int = 0,
    leader_links: int = 1,
    radius: Optional[float] = None,
    seed: int = 1,
) -> Scenario:
    """A generated scenario, as ``formation generate`` writes it: followers
    on formation slots behind the leader, a ring, grid, random-geometric,
    complete or line graph, the nearest ``leader_links`` hearing the leader."""
    return Scenario(_formation.RawScenario.generate(followers, graph, chords, leader_links, radius, seed))


class PaperTable:
    """Table I or II of the paper as numbers: velocity RMSE ×10⁻² per
    follower, in the paper's column order (``COLUMNS``), over seeds.

    ``values``: (seeds, followers, 4) float64, every run's own figure;
    ``mean`` and ``std`` over the seeds; ``paper``: the paper's (4, 4);
    ``ids``: the followers' ids, ``seeds``: the seeds run.
    """

    COLUMNS = ("linear KF", "linear ASIF", "angular KF", "angular ASIF")
    __slots__ = ("title", "seeds", "ids", "values", "paper")

    def __init__(self, raw: Dict[str, Any]):
        self.title: str = raw["title"]
        self.seeds: List[int] = list(raw["seeds"])
        self.ids: List[int] = list(raw["ids"])
        self.values: np.ndarray = raw["values"]
        self.paper: np.ndarray = raw["paper"]

    @property
    def mean(self) -> np.ndarray:
        return self.values.mean(axis=0)

    @property
    def std(self) -> np.ndarray:
        """The sample standard deviation over the seeds (0 for one seed)."""
        n = self.values.shape[0]
        return self.values.std(axis=0, ddof=1) if n > 1 else np.zeros_like(self.values[0])

    def ratio(self) -> np.ndarray:
        """ASIF over KF per follower and channel (linear, angular), of the
        means: (followers, 2); the paper's is ``paper_ratio()``."""
        m = self.mean
        return np.stack([m[:, 1] / m[:, 0], m[:, 3] / m[:, 2]], axis=1)

    def paper_ratio(self) -> np.ndarray:
        p = self.paper
        return np.stack([p[:, 1] / p[:, 0], p[:, 3] / p[:, 2]], axis=1)

    def __repr__(self) -> str:
        lines = [f"{self.title}, mean of {len(self.seeds)} seed(s) (paper in brackets)"]
        lines.append("follower  " + "  ".join(f"{c:>20}" for c in self.COLUMNS))
        for i, fid in enumerate(self.ids):
            paper = self.paper[i] if i < len(self.paper) else [float("nan")] * 4
            cells = [f"{self.mean[i, j]:8.3f} ({paper[j]:5.2f})" for j in range(4)]
            lines.append(f"{fid:>8}  " + "  ".join(f"{c:>20}" for c in cells))
        return "\n".join(lines)


class Claim:
    """One statement of the paper (docs/model.md §12) checked on the runs,
    as ``formation paper``'s ``claims.csv`` gives it.

    ``claim``: the statement; ``quantity`` (in ``unit``): what is measured
    per seed, ``values`` (float64, one per seed); ``required``: the
    condition as text, ``condition`` as numbers (``("<=", bound)``, or
    ``("near", target, tolerance)``); ``holds``: the seeds it holds for;
    ``result``: ``"PASS"`` (every seed), ``"FAIL"`` or ``"N/A"`` (not
    measurable in these runs: ``missing`` says why); ``measured``: the
    values summarised as the report writes them.
    """

    __slots__ = ("claim", "quantity", "unit", "cases", "values", "required", "condition", "holds", "result",
                 "missing", "measured")

    def __init__(self, raw: Dict[str, Any]):
        self.claim: str = raw["claim"]
        self.quantity: str = raw["quantity"]
        self.unit: str = raw["unit"]
        self.cases: List[str] = list(raw["cases"])
        self.values: np.ndarray = raw["values"]
        self.required: str = raw["required"]
        self.condition: tuple = tuple(raw["condition"])
        self.holds: int = raw["holds"]
        self.result: str = raw["result"]
        self.missing: Optional[str] = raw["missing"]
        self.measured: str = raw["measured"]

    @property
    def passed(self) -> bool:
        return self.result == "PASS"

    def __repr__(self) -> str:
        if self.result == "N/A":
            return f"N/A   {self.claim}: {self.missing}"
        return f"{self.result:<4}  {self.claim}: {self.measured} {self.unit} (required {self.required})"


class Paper:
    """What ``formation paper`` checks, from one set of runs: Tables I
    (normal case) and II (fault at 10 s) as :class:`PaperTable` s
    (``table1``, ``table2``), and every claim of the paper as a
    :class:`Claim` (``claims``; ``passed`` when every one passes)."""

    __slots__ = ("table1", "table2", "claims")

    def __init__(self, raw: Dict[str, List[Dict[str, Any]]]):
        self.table1, self.table2 = (PaperTable(t) for t in raw["tables"])
        self.claims: List[Claim] = [Claim(c) for c in raw["claims"]]

    @property
    def passed(self) -> bool:
        return all(c.passed for c in self.claims)

    def claim(self, words: str) -> Claim:
        """The first claim whose statement contains ``words``."""
        for c in self.claims:
            if words in c.claim:
                return c
        raise KeyError(f"no claim says {words!r}; the claims: {[c.claim for c in self.claims]}")

    def __repr__(self) -> str:
        if not self.claims:
            return f"{self.table1!r}\n\n{self.table2!r}"
        counts = {r: sum(c.result == r for c in self.claims) for r in ("PASS", "FAIL", "N/A")}
        head = f"claims: {counts['PASS']} pass, {counts['FAIL']} fail, {counts['N/A']} not measurable"
        return "\n".join([f"{self.table1!r}", "", f"{self.table2!r}", "", head] + [f"  {c!r}" for c in self.claims])


def paper(scenario: Union[Scenario, PathLike] = "paper", seeds: int = 20, threads: Optional[int] = None,
          claims: bool = True) -> Paper:
    """The paper over ``seeds`` seeds (the scenario's seed s, s+1, …):
    every case ``formation paper`` runs (the proposed method, conventional
    backstepping, conventional and super-twisting SMC, KF and ASIF normal
    and with the fault at 10 s, zero-initialised estimates), on the
    scenario's other keys as given; Tables I and II and every claim checked
    on those runs. ``claims=False`` runs only the tables' four cases (KF and
    ASIF, normal and fault), in half the time, and checks no claim.
    ``threads``: every core by default; the GIL is released."""
    if not isinstance(scenario, Scenario):
        scenario = Scenario.load(scenario)
    if seeds < 1:
        raise ValueError(f"seeds must be at least 1, not {seeds}")
    threads = threads or os.cpu_count() or 1
    return Paper(_formation.paper(scenario._raw, seeds, threads, claims))
