"""Coverage pooled over several recovery draws (`irc report DIR DIR ...`)."""

import json

import pytest

from irc_torchrl.algorithms.recovery import coverage_interval, format_pooled, pool_coverage
from irc_torchrl.cli import main


def _summary(seed: int, n_agents: int, raw: dict, calibrated: dict | None = None) -> dict:
    """A recovery summary whose marginal intervals covered ``raw[name]`` of the agents (and
    ``calibrated[name]`` once calibrated)."""
    entry = {"parameters": {name: {"coverage": c} for name, c in raw.items()}}
    if calibrated is not None:
        entry["calibrated"] = {"parameters": {n: {"coverage": c} for n, c in calibrated.items()}}
    return {
        "command": "recover",
        "task": "firefly2d",
        "checkpoint": "firefly2d",
        "seed": seed,
        "streams": 2,
        "n_agents": n_agents,
        "n_trials": 100,
        "mistaken": [False] * (n_agents - 1) + [True],
        "methods": {"marginal": entry},
    }


def test_coverage_is_pooled_over_every_agent_of_the_draws_with_its_interval():
    """36 of 40, 40 of 40 and 40 of 40 are 116 of 120, with the interval of that count; a
    method calibrated in two draws of three has no pooled calibrated coverage."""
    pooled = pool_coverage(
        {
            "d0": _summary(0, 40, {"g_v": 0.9, "goal": 0.975}, {"g_v": 0.95, "goal": 1.0}),
            "d1": _summary(1, 40, {"g_v": 1.0, "goal": 0.925}, {"g_v": 0.925, "goal": 0.95}),
            "d2": _summary(2, 40, {"g_v": 1.0, "goal": 0.9}),
        }
    )
    assert pooled["n_agents"] == 120 and pooled["draws"] == ["d0", "d1", "d2"]
    g_v = pooled["methods"]["marginal"]["raw"]["g_v"]
    assert g_v["coverage"] == pytest.approx(116 / 120)
    assert g_v["coverage_ci"] == coverage_interval(116, 120)
    assert g_v["by_draw"] == [0.9, 1.0, 1.0]
    assert pooled["methods"]["marginal"]["raw"]["goal"]["coverage"] == pytest.approx(112 / 120)
    assert set(pooled["methods"]["marginal"]) == {"raw"}
    calibrated = pool_coverage(
        {
            "d0": _summary(0, 40, {"g_v": 0.9}, {"g_v": 0.95}),
            "d1": _summary(1, 40, {"g_v": 1.0}, {"g_v": 0.925}),
        }
    )
    assert calibrated["methods"]["marginal"]["calibrated"]["g_v"]["coverage"] == 75 / 80
    table = format_pooled(calibrated).splitlines()
    assert table[0] == "coverage over 2 draws, 80 agents"
    low, high = coverage_interval(75, 80)
    assert table[-1].split() == ["g_v", "0.938", f"[{low:.3f},", f"{high:.3f}]", "0.950", "0.925"]


def _changed(summary: dict, **fields) -> dict:
    return {**summary, **fields}


D0 = _summary(0, 40, {"g_v": 0.9})


@pytest.mark.parametrize(
    "other, message",
    [
        (None, r"^summaries: expected two recovery draws or more, got 1$"),
        (_summary(0, 40, {"g_v": 0.9}), r"^d1: the same draw as d0 \(seed 0\): expected draws of"),
        (_changed(D0, seed=None), r"^d1: no seed recorded \(seed None\)"),
        (_summary(1, 40, {"g_w": 0.9}), r"^d1: shape marginal: g_w, d0's marginal: g_v; expected"),
        (_changed(D0, seed=1, n_trials=40), r"^d1: n_trials 40, d0's 100; expected draws of one"),
        (_changed(D0, seed=1, command="demo"), r"^d1: command demo, d0's recover; expected"),
        (_changed(D0, seed=1, checkpoint="r.pt"), r"^d1: checkpoint r.pt, d0's firefly2d;"),
        (_summary(1, 30, {"g_v": 0.9}), r"^d1: n_agents 30, d0's 40; expected draws of one"),
        ({k: v for k, v in _changed(D0, seed=1).items() if k != "streams"},
         r"^d1: streams unrecorded, d0's 2; expected draws of one recovery experiment$"),
        ({"command": "fit", "recordings": []}, r"^d1: not a recovery experiment's summary .*≥ 1"),
        ([1, 2], r"^d1: not a recovery experiment's summary"),
        (_changed(D0, seed=1, n_agents=True), r"^d1: not a recovery experiment's summary"),
        (_summary(1, 40, {"g_v": 0.91}), r"^d1: methods.marginal.parameters.g_v.coverage: expected "
         r"a share of the 40 agents, got 0.91$"),
        (_summary(1, 40, {"g_v": None}), r"^d1: methods.marginal.parameters.g_v.coverage: .*None"),
        (_summary(1, 40, {"g_v": 1.5}), r"^d1: methods.marginal.parameters.g_v.coverage: .*1.5$"),
        (_summary(1, 40, {"g_v": 0.9}, {"g_w": 0.9}),
         r"^d1: methods.marginal.calibrated.parameters: expected scores of g_v$"),
        (_changed(D0, seed=1, methods={"marginal": {"parameters": [1]}}),
         r"^d1: methods.marginal.parameters: expected per-parameter scores$"),
    ],
)  # fmt: skip
def test_what_cannot_be_pooled_is_refused_naming_the_draw_and_field(other, message):
    summaries = {"d0": D0} if other is None else {"d0": D0, "d1": other}
    with pytest.raises(ValueError, match=message) as error:
        pool_coverage(summaries)
    assert "\n" not in str(error.value)


def test_irc_report_of_several_draws_prints_their_pooled_coverage_and_writes_nothing(
    tmp_path, capsys
):
    folders = []
    for seed, covered in ((0, 0.9), (1, 1.0)):
        folder = tmp_path / f"d{seed}"
        folder.mkdir()
        (folder / "summary.json").write_text(json.dumps(_summary(seed, 40, {"g_v": covered})))
        folders.append(str(folder))
    assert main(["report", *folders]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[:2] == ["coverage over 2 draws, 80 agents", "marginal, raw intervals:"]
    assert out[2].split()[:2] == ["g_v", "0.950"]
    assert sorted(p.name for p in tmp_path.rglob("*")) == [
        "d0",
        "d1",
        "summary.json",
        "summary.json",
    ]
    (tmp_path / "d1" / "summary.json").write_text(json.dumps(_summary(0, 40, {"g_v": 1.0})))
    assert main(["report", *folders]) == 2
    assert "the same draw as" in capsys.readouterr().err
    assert main(["report", folders[0], f"{tmp_path}/d1/../d0"]) == 2
    assert (
        f"DIR: {tmp_path}/d1/../d0 given twice; expected each draw once" in capsys.readouterr().err
    )
    setting_like = tmp_path / "lr=3e-3"  # a folder named like a setting is a folder
    setting_like.mkdir()
    (setting_like / "summary.json").write_text(json.dumps(_summary(5, 40, {"g_v": 1.0})))
    assert main(["report", folders[0], str(setting_like)]) == 0
    assert main(["report", folders[0], "runs/lr=3e-3"]) == 2
    assert "error: no summary.json in runs/lr=3e-3" in capsys.readouterr().err
