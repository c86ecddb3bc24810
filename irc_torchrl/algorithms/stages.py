"""The finished fits of a long run, kept in its output folder so that a run stopped part-way
(a killed job, a cluster's time limit) resumes where it stopped, with the same numbers.

Each fit of a run (one estimator on the recorded trials, or on one calibration dataset) is a
stage, saved as ``stages/NAME.pt`` once finished, tensors and plain values only (read back
with ``torch.load(weights_only=True)``), beside a key: a digest of everything the fit depends
on (the run's settings, the policy's checkpoint, the recorded data, the library's code and
torch's version). A run that resumes reads a stage instead of fitting only where the keys
match; any other stage is fitted again.
"""

from __future__ import annotations

import functools
import hashlib
import inspect
import json
import time
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDictBase

import irc_torchrl
from irc_torchrl.algorithms.fit import FitResult
from irc_torchrl.checkpoint import read_weights
from irc_torchrl.config import config_to_dict
from irc_torchrl.data.files import atomic_path
from irc_torchrl.envs.model import TaskModel

__all__ = ["AFTER_FITS", "Stages", "fit_settings", "stage_key"]

#: the settings that act only once the fits are done (a check of them, how many datasets
#: calibrate their intervals and how the factors read their tails): a rerun that changes them
#: reuses the fits, and one with more calibration datasets the refits already done
AFTER_FITS = ("particles", "calibrate", "calibration_tail")


def fit_settings(config: Any) -> dict[str, Any]:
    """The fields of a run's config (a dataclass) its fits depend on: all but
    :data:`AFTER_FITS`."""
    settings = config_to_dict(config)
    for name in AFTER_FITS:
        settings.pop(name, None)
    return settings


def stage_key(
    settings: Mapping[str, Any],
    checkpoint: str | Path,
    model: TaskModel | None = None,
    data: Iterable[TensorDictBase] = (),
) -> str:
    """A digest of what a run's fits depend on: its ``settings`` (JSON-like), the policy's
    ``checkpoint`` file, the source of a task of the user's own (``model``), the recorded
    ``data`` in order, and the library's code and torch's version."""
    digest = hashlib.sha256(json.dumps(settings, sort_keys=True, default=str).encode())
    digest.update(hashlib.sha256(Path(checkpoint).read_bytes()).digest())
    if model is not None:
        task = type(model)
        digest.update(f"{task.__module__}.{task.__qualname__}".encode())
        try:
            digest.update(Path(inspect.getfile(task)).read_bytes())
        except (OSError, TypeError):  # a class without a source file: its name alone
            pass
    for trials in data:
        for key in sorted(trials.keys(True, True), key=str):
            value = trials[key].detach().cpu().contiguous()
            digest.update(f"{key}{value.dtype}{list(value.shape)}".encode())
            digest.update(value.reshape(-1).view(torch.uint8).numpy().tobytes())
    digest.update(f"{_code_digest()} torch {torch.__version__}".encode())
    return digest.hexdigest()


@functools.cache
def _code_digest() -> str:
    """A digest of the library's own source (an edited install's stages are not reused)."""
    root = Path(irc_torchrl.__file__).parent
    digest = hashlib.sha256()
    for path in sorted(root.rglob("*.py")):
        digest.update(path.relative_to(root).as_posix().encode())
        digest.update(path.read_bytes())
    return digest.hexdigest()


class Stages:
    """The stages of one run in ``folder`` (``None``: none kept), under the run's ``key``.

    With ``resume``, a stage an earlier run of the same key finished is read instead of
    fitted; ``reused`` names those, in order.
    """

    def __init__(self, folder: str | Path | None = None, key: str = "", resume: bool = False):
        self.folder = None if folder is None else Path(folder)
        self.key = key
        self.resume = resume
        self.reused: list[str] = []

    def fit(
        self, name: str, work: Callable[[], FitResult], device: torch.device | str = "cpu"
    ) -> tuple[FitResult, float]:
        """Stage ``name``'s fit and the seconds it took (an earlier run's, where read), on
        ``device``: ``work()``'s, saved once finished, or one kept by an earlier run."""
        kept = self._read(name) if self.resume else None
        if kept is not None:
            self.reused.append(name)
            return kept[0].to(device), kept[1]
        begin = time.perf_counter()
        result = work()
        seconds = time.perf_counter() - begin
        if self.folder is not None:
            stage = {"key": self.key, "seconds": seconds, "result": result.cpu().state_dict()}
            with atomic_path(self.folder / f"{name}.pt") as tmp:
                torch.save(stage, tmp)
        return result, seconds

    def prune(self) -> None:
        """Remove the stages of other keys (another run's settings, an older library), so
        that those left belong to the run finished beside them."""
        if self.folder is None or not self.folder.is_dir():
            return
        for path in self.folder.glob("*.pt"):
            if self._load(path) is None:
                path.unlink()

    def _read(self, name: str) -> tuple[FitResult, float] | None:
        """Stage ``name`` of this key, or ``None`` where none is kept (or it is unreadable)."""
        if self.folder is None:
            return None
        stage = self._load(self.folder / f"{name}.pt")
        if stage is None:
            return None
        try:
            return FitResult.from_state_dict(stage["result"]), float(stage["seconds"])
        except (KeyError, TypeError, ValueError):
            return None

    def _load(self, path: Path) -> dict | None:
        """The stage file ``path`` if it holds this key, else ``None``."""
        try:
            stage = read_weights(path)
        except ValueError:
            return None
        if not isinstance(stage, dict) or stage.get("key") != self.key:
            return None
        return stage
