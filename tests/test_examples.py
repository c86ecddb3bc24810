"""The tutorials in examples/ run as documented and do what they say (about 40 s together)."""

from __future__ import annotations

import json
import math
import statistics
import subprocess
import sys
from pathlib import Path

import pytest

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def _run(script: str, out: Path) -> tuple[str, dict]:
    done = subprocess.run(
        [sys.executable, str(EXAMPLES / script), "--out", str(out)],
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    return done.stdout, json.loads((out / "results.json").read_text())


def test_fit_your_recording_recovers_the_gains_within_their_intervals(tmp_path):
    stdout, fit = _run("fit_your_recording.py", tmp_path)
    # the recording is in cm and degrees, read back in m and rad
    header = (tmp_path / "session.csv").read_text().splitlines()[0]
    assert header == "trial,time,x,y,heading,v,w,a_v,a_w,target_x,target_y"
    assert "read" in stdout and "30 trials" in stdout
    for name in ("g_v", "g_w"):  # well identified: the marginal fit's interval holds the truth
        truth = fit["theta_true"][name]
        assert fit["identified"][name]
        assert fit["ci_low"][name] <= truth <= fit["ci_high"][name]
        assert fit["theta_hat"][name] == pytest.approx(truth, rel=0.03)
        assert f"{truth:>6.3f}  yes" in stdout
    assert fit["converged"]
    assert (tmp_path / "beliefs.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_assemble_in_torchrl_trains_ddpg_and_steps_the_inverse(tmp_path):
    stdout, results = _run("assemble_in_torchrl.py", tmp_path)
    ddpg, inverse = results["ddpg"], results["inverse"]
    assert ddpg["updates"] == 12 and len(ddpg["losses"]) == 12
    assert results["finite"]
    assert all(math.isfinite(v) for row in ddpg["losses"] for v in row.values())
    assert ddpg["target_moved"] > 0  # SoftUpdate moved the target networks
    nll = inverse["nll"]
    assert len(nll) == 10 and all(math.isfinite(v) for v in nll)
    assert nll[-1] < nll[0]  # Adam on θ and the motor noise lowers the negative log-likelihood
    assert "DDPG: 12 updates" in stdout and "IRC: negative log-likelihood" in stdout


def test_every_part_the_readme_lists_is_importable_where_it_says():
    """The README's parts table names each public piece and the module to import it from."""
    import importlib
    import re

    readme = (EXAMPLES.parent / "README.md").read_text()
    table = readme.split("| part | where |")[1].split("\n\n")[0]
    not_ours = {"EnvBase", "LossModule", "theta", "task_theta"}  # TorchRL's, and TensorDict keys
    checked = 0
    for row in table.splitlines()[2:]:
        part, where = row.strip("|").split("|")
        names = [n for n in re.findall(r"`([A-Za-z_]\w*)`", part) if n not in not_ours]
        modules, base = [], ""
        for module in re.findall(r"`([\w.]+)`", where):
            base = module if module.startswith("irc_torchrl") else base.rsplit(".", 1)[0] + module
            modules.append(importlib.import_module(base))
        for name in names:
            assert any(hasattr(m, name) for m in modules), (name, [m.__name__ for m in modules])
            checked += 1
    assert checked >= 25, checked  # 29 names today: the parser must not silently skip rows


def test_plan_an_experiment_predicts_intervals_that_narrow_with_the_trials(tmp_path):
    stdout, plan = _run("plan_an_experiment.py", tmp_path)
    few, many = plan["widths"]["25"], plan["widths"]["200"]
    assert all(many[name] < few[name] for name in few)
    # 8 times the trials: 1/√trials gives 2.83 (measured median 3.7 over the 8 parameters)
    ratio = statistics.median(few[name] / many[name] for name in few)
    assert 2.4 < ratio < 5.0, ratio
    # the gains are read off every action: a tenth of their prior range within 25 trials
    assert plan["pinned"]["g_v"] == plan["pinned"]["g_w"] == 25
    assert "pinned from" in stdout
