"""Bring your own law (agents/law_api.py, agents/plugged.py, agents/laws/, docs/laws.md):
how a law is named and refused, the two bundled laws on `lab` and `paper-consistent`
without contact, a law that misbehaves contained and named, and `omnifleet compare`."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import pytest

from agents.law_api import BehaviorLaw, TorqueLaw
from agents.laws import LawError, load, params_of
from deploy.contract.scenario import ScenarioError, load_scenario
from deploy.report.metrics import compute_metrics
from deploy.report.verdict import judge, verdict_line
from deploy.run.run_figures import law_fault_figures
from deploy.run.runner import run_in_process

REPO = Path(__file__).resolve().parents[2]
BAD = str(REPO / "tests" / "laws" / "misbehaving.py")


def _run(scenario: str, law: str, duration: float | None = None, plant: str = "model"):
    sc = load_scenario(scenario).with_law(law)
    res = run_in_process(sc, plant, duration)
    m = compute_metrics(sc, res.series, res.plant, "lockstep", res.wall_time_s,
                        contact_log=res.contacts)
    m |= law_fault_figures(res.law_faults)
    return sc, res, m


# -- naming a law ------------------------------------------------------------------------
def test_every_form_of_a_law_s_name_resolves():
    assert load("paper") is None
    assert load("consensus").level == "behavior" and issubclass(load("consensus"), BehaviorLaw)
    assert issubclass(load("consensus-pd"), TorqueLaw)
    assert load("agents.laws.consensus:ConsensusLaw") is load("consensus")
    assert load(f"{BAD}:Raises").name == "raises"


@pytest.mark.parametrize(("spec", "says"), [
    ("consensos", "did you mean 'consensus'"),
    ("no_such_module_here:Law", "does not import: ModuleNotFoundError"),
    ("agents.laws.consensus:Nope", "has no Nope (its laws: ConsensusLaw"),
    (f"{BAD}:NotALaw", "is not a BehaviorLaw or a TorqueLaw"),
    (f"{BAD}:NoStep", "does not define step"),
    ("/no/such/file.py:Law", "not a file"),
])
def test_a_law_that_cannot_be_used_is_named_with_what_is_wrong(spec, says):
    with pytest.raises(LawError, match=None) as exc:
        load(spec)
    assert says in str(exc.value), str(exc.value)


def test_a_law_file_that_raises_on_import_is_refused_naming_the_exception(tmp_path):
    bad = tmp_path / "broken.py"
    bad.write_text("import math\nraise RuntimeError('half-written law')\n")
    with pytest.raises(LawError, match="does not import: RuntimeError: half-written law"):
        load(f"{bad}:Law")


def test_parameters_are_checked_by_the_law_s_own_declaration():
    cls = load("consensus")
    assert params_of(cls, {"gamma": 3}, "consensus").gamma == 3.0  # TOML's 3 for 3.0
    with pytest.raises(LawError, match="no parameter 'gama'; did you mean 'gamma'"):
        params_of(cls, {"gama": 1.0}, "consensus")
    with pytest.raises(LawError, match="parameter 'gamma' must be a float"):
        params_of(cls, {"gamma": "fast"}, "consensus")
    with pytest.raises(LawError, match="must be finite"):
        params_of(cls, {"gamma": math.inf}, "consensus")
    with pytest.raises(LawError, match="takes no \\[law\\] params"):
        params_of(None, {"gamma": 1.0}, "paper")


def test_a_scenario_names_its_law_and_a_bad_one_is_refused_on_load(tmp_path):
    text = (REPO / "deploy" / "scenarios" / "lab.toml").read_text()
    good = tmp_path / "lab-consensus.toml"
    good.write_text(text + '\n[law]\nuse = "consensus"\nparams = { gamma = 1.5 }\n')
    sc = load_scenario(good)
    assert sc.law_name == "consensus" and sc.law()[1].gamma == 1.5
    bad = tmp_path / "lab-bad.toml"
    bad.write_text(text + '\n[law]\nuse = "consensus"\nparams = { gama = 1.5 }\n')
    with pytest.raises(ScenarioError, match="law.use: law 'consensus': no parameter 'gama'"):
        load_scenario(bad)
    relative = tmp_path / "lab-file.toml"  # a law file beside the scenario, named relatively
    (tmp_path / "mylaw.py").write_text("from agents.laws.consensus import ConsensusLaw as Mine\n")
    relative.write_text(text + '\n[law]\nuse = "mylaw.py:Mine"\n')
    assert load_scenario(relative).law()[0].__name__ == "ConsensusLaw"


# -- the bundled laws: to the end, no contact ---------------------------------------------
@pytest.mark.slow
@pytest.mark.parametrize("law", ["consensus", "consensus-pd"])
@pytest.mark.parametrize("scenario", ["lab", "paper-consistent"])
def test_a_bundled_law_runs_the_scenario_to_the_end_without_contact(law, scenario):
    sc, res, m = _run(scenario, law)
    assert res.series.steps == sc.steps and not res.interrupted
    assert m["contacts"] == 0 and m["min_obstacle_gap_m"] > 0 and m["min_robot_gap_m"] > 0
    assert all(f["errors"] == 0 and f["refused"] == 0 for f in m["law_faults"])
    assert m["law"] == law and m["nonfinite_commands"] == 0


def test_the_consensus_law_keeps_the_formation_on_lab():
    """Ren and Beard's tracking (C1) with the paper's dynamic level: every robot settles
    within the paper's bound and ends within 5 cm of its formation position."""
    _, _, m = _run("lab", "consensus")
    assert judge(m)["pass"], judge(m)["reasons"]
    assert max(m["formation_distance_end_m"]) < 0.05


# -- a law that misbehaves ------------------------------------------------------------
@pytest.mark.parametrize(("cls", "kind", "says"), [
    ("Raises", "errors", "raises.step: ZeroDivisionError: division by zero (" + BAD),
    ("Nan", "refused", "nan.step at t = 1.000 s returned BehaviorOutput(v_d=(nan"),
    ("Absurd", "refused", "absurd.step at t = 1.000 s returned BehaviorOutput(v_d=(1000000000.0"),
])
def test_a_misbehaving_law_is_braked_counted_and_named_and_nothing_touches(cls, kind, says):
    sc, res, m = _run("lab", f"{BAD}:{cls}", duration=3.0)
    f = m["law_faults"]
    assert all(x[kind] == 400 for x in f), f  # every step from 1 s to 3 s, each robot
    assert f[0]["error"].startswith(says), f[0]["error"]
    assert m["contacts"] == 0 and m["nonfinite_commands"] == 0
    v = judge(m)
    assert not v["pass"] and not v["law_sound"]
    assert f"law {sc.law_name} on robot #1: " in verdict_line(v)
    # braked: each robot slower after 2 s than at 1 s (v_d = 0 through the controller)
    import numpy as np

    speed = np.linalg.norm(res.series.q_dot[:, :, :2], axis=2)
    assert (speed[-1] < speed[int(1.0 / sc.dt)] + 1e-9).all()


def test_a_law_slower_than_its_period_is_counted_and_named():
    sc, _, m = _run("lab", f"{BAD}:Slow", duration=2.0)  # 3 ms a step of 5 ms: no overrun
    assert m["law_overruns"] == [0, 0, 0]
    fast = load_scenario("lab").with_control_rate(500.0).with_law(f"{BAD}:Slow")  # 2 ms
    res = run_in_process(fast, "model", 1.5)
    mm = compute_metrics(fast, res.series, "model", "lockstep", res.wall_time_s)
    mm |= law_fault_figures(res.law_faults)
    assert all(n == 250 for n in mm["law_overruns"])  # 1.0 .. 1.5 s at 500 Hz
    assert "took longer than its period in 250 of 750 steps" in verdict_line(judge(mm))


def test_a_law_gets_copies_of_its_inputs():
    """Meddles empties the neighbours' shares it was given: the runtime's are whole, and
    its neighbours read on (the run equals the consensus law's with no neighbour term)."""
    from agents.law_api import LawInputs

    sc = load_scenario("lab").with_law(f"{BAD}:Meddles")
    res = run_in_process(sc, "model", 0.2)
    assert res.series.steps == 40 and res.law_faults[2]["errors"] == 0
    with pytest.raises(AttributeError):  # the inputs themselves are frozen
        LawInputs(0, 0.005, (0, 0, 0), (0, 0, 0), None, {}, (), ()).t = 1.0  # type: ignore[misc]


# -- the command line ---------------------------------------------------------------
def _omnifleet(*args: str, cwd: Path = REPO) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "deploy.cli", *args], cwd=cwd,
                          capture_output=True, text=True, timeout=300)


@pytest.mark.parametrize("law", ["nope", f"{BAD}:NotALaw", "/tmp/no-such-law.py:X"])
def test_run_refuses_a_law_it_cannot_use_before_any_process_starts(law, tmp_path):
    r = _omnifleet("run", "lab", "--law", law, "--out", str(tmp_path / "run"))
    assert r.returncode == 2, r.stderr
    assert "law" in r.stderr and not (tmp_path / "run").exists()


@pytest.mark.slow
def test_compare_writes_its_table_figure_and_runs(tmp_path):
    r = _omnifleet("compare", "lab", "--laws", "paper,consensus", "--duration", "4",
                   "--plant", "model", "--out", str(tmp_path))
    assert r.returncode == 0, r.stderr + r.stdout
    runs = json.loads((tmp_path / "compare.json").read_text())["runs"]
    assert [x["law"] for x in runs] == ["paper", "consensus"]
    assert all(x["contacts"] == 0 and x["cpu_us_per_robot_step"] > 0 for x in runs)
    table = (tmp_path / "compare.md").read_text()
    assert "| paper | 1 |" in table and "| consensus | 1 |" in table
    assert (tmp_path / "compare.png").stat().st_size > 10_000
    assert _omnifleet("compare", "lab", "--laws", "paper,nope").returncode == 2


def test_the_example_of_docs_laws_runs_as_printed(tmp_path):
    """docs/laws.md's law, as the page prints it, named by its file: lab for 3 s, no error,
    no contact."""
    import re

    text = (REPO / "docs" / "laws.md").read_text()
    code = re.search(r"```python\n(.*?)```", text, re.S).group(1)
    (tmp_path / "mylaws.py").write_text(code)
    sc, res, m = _run("lab", f"{tmp_path / 'mylaws.py'}:GoToSlot", duration=3.0)
    assert m["law"] == "go-to-slot" and m["contacts"] == 0
    assert all(f["errors"] == 0 and f["refused"] == 0 for f in m["law_faults"])
