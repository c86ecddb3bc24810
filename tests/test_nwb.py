"""NWB files (needs pynwb): trial numbers the trials table cannot hold are refused."""

from __future__ import annotations

import pytest
import torch

from irc_torchrl.algorithms.simulate import simulate_agents
from irc_torchrl.data.io import read_trials, write_trials
from irc_torchrl.envs import Firefly2DModel

pytest.importorskip("pynwb")


def _numbered(model: Firefly2DModel, numbers: list[float]):
    """Random-action trials with at least two recorded steps, numbered ``numbers``."""
    theta = model.theta_space.default().unsqueeze(0)
    trials = simulate_agents(model, None, theta, 8, seed=0)[0]
    trials = trials[trials["mask"].sum(-1) >= 2][: len(numbers)]
    trials["trial"] = torch.tensor(numbers, dtype=torch.float64)[:, None].expand(trials.shape)
    return trials


def test_non_integer_trial_numbers_are_refused_before_writing(tmp_path):
    """0.1, 0.2 and 0.3 would all be written as trial 0: a file that cannot be read back."""
    model = Firefly2DModel()
    with pytest.raises(ValueError, match="NWB: field 'trial' is 0.1 at row 0; expected integer"):
        write_trials(_numbered(model, [0.1, 0.2, 0.3]), tmp_path / "t.nwb", model)
    assert list(tmp_path.iterdir()) == []
    write_trials(_numbered(model, [3.0, 5.0, 7.0]), tmp_path / "t.nwb", model)
    back = read_trials(tmp_path / "t.nwb", model)
    assert back["trial"][:, 0].tolist() == [3, 5, 7]
