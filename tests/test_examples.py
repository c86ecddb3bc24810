"""The tutorials in examples/ run as documented and do what they say (about a minute together)."""

from __future__ import annotations

import importlib.util
import json
import math
import statistics
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def _run(script: str, out: Path, *args: str) -> tuple[str, dict]:
    done = subprocess.run(
        [sys.executable, str(EXAMPLES / script), "--out", str(out), *args],
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    return done.stdout, json.loads((out / "results.json").read_text())


def test_fit_your_recording_recovers_the_gains(tmp_path):
    stdout, fit = _run("fit_your_recording.py", tmp_path)
    # the recording is in cm and degrees, read back in m and rad
    header = (tmp_path / "session.csv").read_text().splitlines()[0]
    assert header == "trial,time,x,y,heading,v,w,a_v,a_w,target_x,target_y"
    assert "read" in stdout and "30 trials" in stdout
    for name in ("g_v", "g_w"):  # well identified: within 3% (measured 1.5% and 0.7%)
        truth = fit["theta_true"][name]
        assert fit["identified"][name]
        assert fit["theta_hat"][name] == pytest.approx(truth, rel=0.03)
        covered = fit["ci_low"][name] <= truth <= fit["ci_high"][name]
        assert f"{truth:>6.3f}  {'yes' if covered else 'no'}" in stdout
    # one agent's raw intervals: g_w's holds the truth, g_v's (±0.4%) misses it by 1.5%
    assert fit["ci_low"]["g_w"] <= fit["theta_true"]["g_w"] <= fit["ci_high"]["g_w"]
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
    not_ours = {"EnvBase", "LossModule", "ObservationNorm", "theta", "task_theta"}  # not ours
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
    # 3 agents (the example's 6 take 1.5× as long)
    stdout, plan = _run("plan_an_experiment.py", tmp_path, "--agents", "3")
    few, many = plan["widths"]["25"], plan["widths"]["200"]
    assert all(many[name] < few[name] for name in few)
    # 8 times the trials: 1/√trials gives 2.83 (measured median 3.1 over the 8 parameters;
    # 3.7 with 6 agents)
    ratio = statistics.median(few[name] / many[name] for name in few)
    assert 2.4 < ratio < 5.0, ratio
    # the gains are read off every action: a tenth of their prior range within 25 trials
    assert plan["pinned"]["g_v"] == plan["pinned"]["g_w"] == 25
    assert "pinned from" in stdout


def _load_example(name: str):
    """An example script as a module (its ``main`` not run)."""
    spec = importlib.util.spec_from_file_location(name, EXAMPLES / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_define_your_task_fits_an_own_task_family_by_both_estimators(tmp_path):
    """The example's reach-and-hold task, written there alone, runs through simulation and
    Algorithm 2 (seed 0). Tolerances: the marginal θ̂ within a tenth of each prior range of θ*
    (map, biased, within a fifth), at least 8 of the 9 marginal 95% intervals holding θ*, the
    marginal motor noise within 15% of θ*'s, its log-likelihood at θ* a particle filter's to
    2 nats per agent, and map's at least 20 nats below it with the motor noise inflated."""
    stdout, results = _run("define_your_task.py", tmp_path)
    returns = results["returns"]
    assert returns["controller"]["return"] > returns["random"]["return"] + 1
    assert returns["controller"]["final_distance"] < 0.1 < returns["random"]["final_distance"]
    space = _load_example("define_your_task").reach_theta_space()
    ranges = {name: space[name].high - space[name].low for name in space.free_names}
    for method, share in (("marginal", 0.1), ("map", 0.2)):
        fitted = results[method]
        assert len(fitted["agents"]) == len(results["theta_true"]) == 3
        for truth, agent in zip(results["theta_true"], fitted["agents"], strict=True):
            assert agent["converged"]
            assert agent["theta_hat"]["sigma_v"] == pytest.approx(truth["sigma_v"]) == 0.05
            for name, width in ranges.items():
                assert abs(agent["theta_hat"][name] - truth[name]) < share * width, (method, name)
    marginal, map_ = results["marginal"], results["map"]
    covered = sum(
        agent["ci_low"][name] <= truth[name] <= agent["ci_high"][name]
        for truth, agent in zip(results["theta_true"], marginal["agents"], strict=True)
        for name in ranges
    )
    assert covered >= 8, covered
    assert all(abs(noise - 0.1) < 0.015 for noise in marginal["motor_noise"])
    assert all(abs(gap) < 2 for gap in marginal["gap_at_truth"])
    assert all(gap < -20 for gap in map_["gap_at_truth"])
    assert all(m > n for m, n in zip(map_["motor_noise"], marginal["motor_noise"], strict=True))
    assert "marginal (" in stdout and "95% interval" in stdout and "wrote" in stdout


def test_define_your_task_model_passes_the_librarys_checks():
    """The example's TaskModel as the library needs it: TorchRL's spec check of the env with
    the belief filter and belief reward; a calibrated filter (agent θ = world θ, random
    controls: the normalised error of the belief, χ² with 2 dof, averages 2 ± 0.25 over 256
    trials × 40 steps) with symmetric positive-definite covariances; the default Jacobians
    (by torch.func) the linear task's own; belief features whose arguments broadcast."""
    from torchrl.envs import Compose, TransformedEnv
    from torchrl.envs.utils import check_env_specs

    from irc_torchrl.envs import BeliefReward, EKFBelief, TaskEnv

    example = _load_example("define_your_task")
    model = example.ReachModel()
    env = TransformedEnv(
        TaskEnv(model, batch_size=(256,), seed=0), Compose(EKFBelief(model), BeliefReward(model))
    )
    check_env_specs(env, seed=0)
    rollout = env.rollout(model.max_steps, break_when_any_done=False)
    cov = rollout["next", "belief", "cov"].double()
    assert torch.equal(cov, cov.mT)
    assert (torch.linalg.eigvalsh(cov) > 0).all()
    error = (rollout["next", "state"] - rollout["next", "belief", "mean"]).double().unsqueeze(-1)
    nees = (error.mT @ torch.linalg.solve(cov, error)).mean().item()
    assert abs(nees - 2) < 0.25, nees

    state, action = torch.randn(7, 2), torch.rand(7, 1) * 2 - 1
    theta = model.theta_space.sample((7,), generator=torch.Generator().manual_seed(0))
    jacobian = torch.tensor([[1.0, model.dt], [0.0, 1.0]]).expand(7, 2, 2)
    torch.testing.assert_close(model.transition_jacobian(state, action, theta), jacobian)
    observed = torch.tensor([[0.0, 1.0]]).expand(7, 1, 2)
    torch.testing.assert_close(model.observation_jacobian(state, theta), observed)

    # as the hard E-step passes them: beliefs at every step, each trial's target and θ once
    mean, cov = torch.randn(2, 3, 5, 2), torch.eye(2).expand(2, 3, 5, 2, 2)
    target, step = torch.zeros(2, 3, 1, 1), torch.arange(5).view(1, 1, 5, 1)
    features = model.belief_features(mean, cov, target, step, theta[:6].view(2, 3, 1, 4))
    assert features.shape == (2, 3, 5, model.belief_feature_dim + model.theta_space.dim)


def test_define_your_task_controller_applies_the_lqr_gain_of_the_agents_own_theta():
    """The example's controller is the continuous-time LQR gain of ``ẍ = g a`` under the cost
    ``e² + c a²`` (the Riccati equation solved by scipy) at the agent's own g and c, read from
    the θ at the end of its belief features."""
    from scipy.linalg import solve_continuous_are

    example = _load_example("define_your_task")
    model = example.ReachModel()
    controller = example.LQGController(model)
    state = torch.tensor([[0.3, -0.2], [-0.5, 0.4]], dtype=torch.float64)
    target = torch.tensor([[0.1], [0.2]], dtype=torch.float64)
    cov = 0.01 * torch.eye(2, dtype=torch.float64).expand(2, 2, 2)
    for gain, cost in ((1.0, 0.1), (1.3, 0.05), (0.8, 0.2), (1.6, 0.3)):
        theta = model.theta_space.from_dict({"g": gain, "effort_cost": cost}).double()
        features = model.belief_features(
            state, cov, target, torch.zeros(2, 1), theta.expand(2, -1)
        )
        riccati = solve_continuous_are(
            np.array([[0.0, 1.0], [0.0, 0.0]]), np.array([[0.0], [gain]]), np.diag([1.0, 0.0]),
            np.array([[cost]]),
        )  # fmt: skip
        lqr = np.array([[0.0, gain]]) @ riccati / cost
        error = torch.cat([state[:, :1] - target, state[:, 1:]], -1).numpy()
        expected = -error @ lqr.T
        np.testing.assert_allclose(controller(features).detach().numpy(), expected, rtol=1e-6)

