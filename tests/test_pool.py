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
        "seed": seed,
        "n_agents": n_agents,
        "methods": {"marginal": entry},
    }


def test_coverage_is_pooled_over_every_agent_of_the_draws_with_its_interval():
    """36 of 40 and 40 of 40 are 76 of 80, not the mean of two rates when the draws differ in
    size (30 of 30 beside 36 of 40: 66 of 70); a method calibrated in one draw only has no
    pooled calibrated coverage."""
    pooled = pool_coverage(
        {
            "d0": _summary(0, 40, {"g_v": 0.9, "goal": 0.975}, {"g_v": 0.95, "goal": 1.0}),
            "d1": _summary(1, 40, {"g_v": 1.0, "goal": 0.925}, {"g_v": 0.925, "goal": 0.95}),
            "d2": _summary(2, 30, {"g_v": 1.0, "goal": 0.9}),
        }
    )
    assert pooled["n_agents"] == 110 and pooled["draws"] == ["d0", "d1", "d2"]
    g_v = pooled["methods"]["marginal"]["raw"]["g_v"]
    assert g_v["coverage"] == pytest.approx(106 / 110)
    assert g_v["coverage_ci"] == coverage_interval(106, 110)
    assert g_v["by_draw"] == [0.9, 1.0, 1.0]
    assert pooled["methods"]["marginal"]["raw"]["goal"]["coverage"] == pytest.approx(103 / 110)
    assert set(pooled["methods"]["marginal"]) == {"raw"}
    two = pool_coverage({"a": _summary(0, 30, {"g_v": 1.0}), "b": _summary(1, 40, {"g_v": 0.9})})
    assert two["methods"]["marginal"]["raw"]["g_v"]["coverage"] == pytest.approx(66 / 70)
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


@pytest.mark.parametrize(
    "summaries, message",
    [
        ({"d0": _summary(0, 40, {"g_v": 0.9})}, r"^summaries: expected two recovery draws or more"),
        (
            {"d0": _summary(4, 40, {"g_v": 0.9}), "again": _summary(4, 40, {"g_v": 0.9})},
            r"^again: the same draw as d0 \(seed 4: the same agents\)",
        ),
        (
            {"d0": _summary(0, 40, {"g_v": 0.9}), "d1": _summary(1, 40, {"g_w": 0.9})},
            r"^d1: fits methods and parameters marginal: g_w, d0 marginal: g_v; expected draws",
        ),
        (
            {"d0": _summary(0, 40, {"g_v": 0.9}), "fit": {"command": "fit", "recordings": []}},
            r"^fit: not a recovery experiment's summary .*expected n_agents and methods",
        ),
        (
            {"d0": _summary(0, 40, {"g_v": 0.9}), "list": [1, 2]},
            r"^list: not a recovery experiment's summary",
        ),
    ],
)
def test_what_cannot_be_pooled_is_refused_naming_the_draw(summaries, message):
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
    assert main(["report", *folders]) != 0
    assert "the same draw as" in capsys.readouterr().err
