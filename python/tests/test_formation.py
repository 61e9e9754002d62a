"""The Python package against the command line it is built from.

Run by `cargo test` (tests/it/python.rs), which passes the `formation`
binary as FORMATION_BIN and a free block of loopback ports as
FORMATION_BASE_PORT; by hand: `pip install ./python pytest`, then
`FORMATION_BIN=target/debug/formation pytest python/tests`.
"""

from __future__ import annotations

import csv
import json
import os
import re
import subprocess
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest

import formation

ROOT = Path(__file__).resolve().parents[2]
PAPER = str(ROOT / "scenarios" / "paper.toml")


def cli(*args: str, check: bool = True, timeout: float = 120) -> subprocess.CompletedProcess:
    exe = os.environ.get("FORMATION_BIN")
    if not exe:
        pytest.fail("FORMATION_BIN is not set: the path of the formation binary (cargo build; target/debug/formation)")
    p = subprocess.run([exe, *args], capture_output=True, text=True, timeout=timeout)
    if check and p.returncode != 0:
        pytest.fail(f"formation {' '.join(args)} exited {p.returncode}: {p.stderr.strip()}")
    return p


def csv_columns(path: Path) -> dict:
    with open(path) as f:
        names = f.readline().strip().split(",")
    data = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2, dtype=np.float64)
    return {n: data[:, i] for i, n in enumerate(names)}


def same_bits(a: np.ndarray, b: np.ndarray) -> bool:
    return a.dtype == np.float64 and a.shape == b.shape and np.array_equal(a.view(np.uint64), b.view(np.uint64))


def assert_run_is_folder(run: formation.Run, folder: Path, what: str) -> None:
    for fid, table in run.followers.items():
        file = csv_columns(folder / f"follower_{fid}.csv")
        assert list(file) == table.columns, f"{what}: follower {fid}'s columns {table.columns} vs the CSV's {list(file)}"
        for name, column in file.items():
            a = table[name]
            if not same_bits(a, column):
                bad = np.flatnonzero(a != column) if a.shape == column.shape else []
                first = int(bad[0]) if len(bad) else None
                pytest.fail(
                    f"{what}: follower {fid}'s {name} differs from the CSV ({a.shape} vs {column.shape}, first "
                    f"different row {first}: {a[first] if first is not None else '-'} vs "
                    f"{column[first] if first is not None else '-'})"
                )
    leader = csv_columns(folder / "leader.csv")
    for name, column in leader.items():
        assert same_bits(run.leader[name], column), f"{what}: the leader's {name} differs from leader.csv"


def test_a_scenario_changed_in_python_runs_as_the_command_line_runs_it(tmp_path):
    s = formation.Scenario.load("paper")
    s["duration"] = 4
    s["filter"] = "kf"
    s.set("faults+={link=[1, 2], from=1, to=2.5}")
    s["backstepping.c1"] = 3.5
    assert s["backstepping.c1"] == 3.5 and s["filter"] == "kf" and len(s["faults"]) == 1
    saved = tmp_path / "changed.toml"
    s.save(saved)
    cli("sim", str(saved), "--out", str(tmp_path / "cli"), "-q")
    run = formation.sim(s, threads=2)
    assert run.complete and run.error is None
    assert_run_is_folder(run, tmp_path / "cli", "sim")
    assert run.summary == json.loads((tmp_path / "cli" / "summary.json").read_text())
    assert run.faults and run.faults == run.summary["faults"]
    # The same overrides given to the command line as --set.
    sets = [w for a in s.overrides for w in ("--set", a)]
    cli("sim", PAPER, *sets, "--every", "10", "--out", str(tmp_path / "sets"), "-q")
    assert_run_is_folder(formation.sim(s, every=10), tmp_path / "sets", "sim every 10")


def set_error_cases():
    """Every `--set` case of tests/it/hostile_inputs.rs (sim_paper(...) with
    only --set arguments): the same list the command line is tested with."""
    text = (ROOT / "tests" / "it" / "hostile_inputs.rs").read_text()
    cases = []
    for name, args in re.findall(r'sim_paper\(\s*"([^"]+)",\s*&\[([^\]]*(?:\][^\]]*)*?)\],\s*&\[', text):
        words = re.findall(r'"((?:[^"\\]|\\.)*)"', args)
        if words and len(words) % 2 == 0 and all(w == "--set" for w in words[::2]):
            cases.append(pytest.param(words[1::2], id=name))
    assert len(cases) >= 15, f"only {len(cases)} --set cases found in hostile_inputs.rs"
    return cases


@pytest.mark.parametrize("sets", set_error_cases())
def test_a_bad_set_raises_value_error_with_the_command_lines_message(sets, tmp_path):
    p = cli("sim", PAPER, "--out", str(tmp_path / "out"), "-q", *[w for a in sets for w in ("--set", a)], check=False)
    assert p.returncode == 2, f"--set {sets}: the command line exited {p.returncode}, not 2: {p.stderr}"
    line = p.stderr.strip().splitlines()[-1]
    assert line.startswith("error: "), line
    s = formation.Scenario.load(PAPER)
    before = s.to_dict()
    with pytest.raises(ValueError) as e:
        for a in sets:
            s.set(a)
    assert str(e.value) == line[len("error: ") :]
    assert s.to_dict() == before or len(sets) > 1, "a refused assignment changed the scenario"


def test_keys_values_and_bad_values_from_python():
    s = formation.Scenario.load("paper", duration=3)
    assert s.steps == 3000 and s.dt == 0.001 and s.follower_ids == [1, 2, 3, 4]
    assert s["followers[0].offset"] == [4.0, -4.0]
    s["robot.mass"] = np.float64(12.5)
    s["noise"] = False
    s["faults"] = [{"node": 3, "from": 1.0, "to": 2.0}]
    assert s["robot.mass"] == 12.5 and s["noise"] is False and s["faults"][0]["node"] == 3
    with pytest.raises(KeyError):
        s["robot.weight"]
    with pytest.raises(ValueError, match="Lemma 1"):
        s["edges"] = [[1, 2]]
    with pytest.raises(TypeError):
        s["dt"] = object()
    with pytest.raises(ValueError, match="the built-in scenarios are"):
        formation.Scenario.load("no-such-scenario")
    with pytest.raises(ValueError, match="threads"):
        formation.sim(s, threads=0)
    c = s.with_(filter="kf")
    assert c["filter"] == "kf" and s["filter"] == "asif"
    assert "duration=3" in repr(s)
    # A leader steered live is not simulated: its run is, from its record.
    with pytest.raises(ValueError, match="plays such a run again from its record"):
        formation.sim(formation.Scenario.load("teleop", duration=1))


def test_a_generated_scenario_is_formation_generates(tmp_path):
    out = tmp_path / "ring.toml"
    cli("generate", "--followers", "12", "--graph", "ring", "--chords", "3", "--seed", "7", "--out", str(out))
    g = formation.generate(12, "ring", chords=3, seed=7)
    assert g._raw.text == out.read_text()
    assert len(g.follower_ids) == 12
    with pytest.raises(ValueError, match="unknown"):
        formation.generate(12, "torus")


def test_a_lockstep_launch_read_back_equals_the_simulator(tmp_path):
    base = os.environ.get("FORMATION_BASE_PORT")
    ports = ["--base-port", base] if base else []
    out = tmp_path / "launch"
    cli("launch", PAPER, "--set", "duration=2", "--out", str(out), "-q", *ports, timeout=120)
    run = formation.read_run(out)
    assert run.network is not None and run.complete
    sim = formation.sim(formation.Scenario.load(PAPER, duration=2))
    for fid, table in sim.followers.items():
        for name in table:
            assert same_bits(run.followers[fid][name], table[name]), f"follower {fid}'s {name}: launch ≠ sim"
    for name in sim.leader:
        assert same_bits(run.leader[name], sim.leader[name]), f"leader's {name}: launch ≠ sim"
    with pytest.raises(ValueError, match="no run folder"):
        formation.read_run(tmp_path / "nothing")
    with pytest.raises(ValueError, match="not a run folder"):
        formation.read_run(tmp_path)


def test_python_threads_run_while_a_simulation_runs():
    """The GIL is released while a run runs: another Python thread runs
    Python in the middle of it. The main thread notes the time at every
    turn of a loop while a run of about half a second goes in a second
    thread; with the GIL held, no Python of the main thread could run
    between the run's start and its end (not a turn in its middle 80 %).
    Whatever the machine's speed or load: the operating system runs a
    ready thread within milliseconds, not after half a second. (Threads
    that make runs faster on several cores are `formation bench`'s to
    measure, not a test's.)"""
    s = formation.Scenario.load("paper", duration=400)
    span: list[float] = []

    def run():
        span.append(time.perf_counter())
        formation.sim(s)
        span.append(time.perf_counter())

    with ThreadPoolExecutor(1) as pool:
        done = pool.submit(run)
        turns = []
        while not done.done():
            turns.append(time.perf_counter())
        done.result()
    t0, t1 = span
    d = t1 - t0
    inside = [t for t in turns if t0 + 0.1 * d < t < t1 - 0.1 * d]
    print(f"a run of {d:.3f} s; the main thread turned {len(inside)} times in its middle 80 %")
    assert inside, f"no turn of the main thread during {d:.3f} s of a run in another thread: the GIL was held"


def test_the_paper_tables_are_formation_papers(tmp_path):
    """Tables I and II from Python: the same runs as `formation paper`'s
    tables (its CSVs' min, max and mean per follower and column), the
    paper's values beside them."""
    out = tmp_path / "paper"
    cli("paper", "--seeds", "3", "--set", "duration=12", "--out", str(out), "-q", timeout=300)
    p = formation.paper(formation.Scenario.load("paper", duration=12), seeds=3, threads=2)
    for table, file in [(p.table1, "table1_normal.csv"), (p.table2, "table2_fault.csv")]:
        assert table.values.shape == (3, 4, 4) and table.values.dtype == np.float64
        lines = (out / file).read_text().splitlines()
        head = lines[0].split(",")
        rows = [dict(zip(head, line.split(","))) for line in lines[1:]]
        assert len(rows) == 16, f"{file}: {len(rows)} rows"
        for r in rows:
            col = ["linear", "angular"].index(r["channel"]) * 2 + ["kf", "asif"].index(r["filter"])
            f = table.ids.index(int(r["follower"]))
            got = table.values[:, f, col]
            assert got.min() == float(r["min"]) and got.max() == float(r["max"]), f"{file} {r}: {got}"
            assert abs(got.mean() - float(r["mean"])) <= 1e-12 * abs(float(r["mean"])), f"{file} {r}: {got.mean()}"
            assert table.paper[f, col] == float(r["paper"])
    assert p.table2.ratio().shape == (4, 2)
    assert "Table II" in repr(p)

    # The claims: claims.csv's rows, one for one, from the same runs.
    with open(out / "claims.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert [c.claim for c in p.claims] == [r["claim"] for r in rows]
    for c, r in zip(p.claims, rows):
        assert (c.quantity, c.unit, " ".join(c.cases), c.required, str(c.holds), c.result) == (
            r["quantity"], r["unit"], r["cases"], r["required"], r["holds"], r["result"]), f"{c!r} against {r}"
        assert len(c.values) == int(r["n"]), f"{c!r}: {len(c.values)} values, claims.csv n = {r['n']}"
        if len(c.values):
            assert c.values.min() == float(r["min"]) and c.values.max() == float(r["max"]), f"{c!r}: {c.values}"
            assert abs(c.values.mean() - float(r["mean"])) <= 1e-12 * abs(float(r["mean"])), f"{c!r}: {c.values}"
    # 2 s after the fault are too few for the fault claims: both verdicts compared.
    results = {c.result for c in p.claims}
    assert {"PASS", "FAIL"} <= results, f"a 12 s run both passes claims and fails some: {results}"
    assert not p.passed
    with pytest.raises(ValueError, match="seeds"):
        formation.paper(seeds=0)


def test_the_papers_claims_hold_on_the_paper_scenario():
    """Every claim of docs/model.md §12 passes on the paper's own scenario
    (20 s), checked from Python on 3 seeds, with each claim's numbers."""
    p = formation.paper(seeds=3, threads=2)
    bad = [c for c in p.claims if not c.passed]
    assert p.passed and len(p.claims) >= 12, f"{len(p.claims)} claims; not passing: {bad}"
    jump = p.claim("v_c(0)")
    assert jump.condition[0] == "near" and abs(jump.values - 15.0).max() <= 1e-9, f"{jump!r}: {jump.values}"
    assert "claims: " in repr(p)
    with pytest.raises(KeyError, match="no claim"):
        p.claim("no such words")


def test_a_networked_run_replays_from_python_as_formation_replay(tmp_path):
    base = os.environ.get("FORMATION_BASE_PORT")
    ports = ["--base-port", str(int(base) + 6)] if base else []
    out = tmp_path / "run"
    cli("launch", PAPER, "--set", "duration=1.5", "--set", "faults+={node=3, from=0.5, to=0.8}", "--out", str(out),
        "-q", *ports, timeout=120)
    run = formation.read_run(out)
    again = formation.replay(out)
    assert again.problems == [], again.problems
    model = formation.replay(out, hearing="model")
    sim = formation.sim(formation.Scenario.load(PAPER, duration=1.5).set("faults+={node=3, from=0.5, to=0.8}"))
    for fid in run.followers:
        for name in run.followers[fid]:
            assert same_bits(again.followers[fid][name], run.followers[fid][name]), f"replay: follower {fid} {name}"
            assert same_bits(model.followers[fid][name], sim.followers[fid][name]), f"model: follower {fid} {name}"
    with pytest.raises(ValueError, match="recorded or model"):
        formation.replay(out, hearing="guess")
    with pytest.raises(ValueError):
        formation.replay(tmp_path / "nothing")
