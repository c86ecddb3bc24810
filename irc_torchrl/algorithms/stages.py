"""The finished fits of a long run, kept in its output folder so that a run stopped part-way
(a killed job, a cluster's time limit) resumes where it stopped, with the same numbers.

Each fit of a run (one estimator on the recorded trials, or on one calibration dataset) and
each particle check of a fit is a stage, saved as ``stages/NAME.pt`` once finished, tensors
and plain values only (read back with ``torch.load(weights_only=True)``), beside a key: a
digest of everything the stage depends on (the run's settings, the policy's checkpoint, the
task, the trials, the library's code and the versions of torch, torchrl and tensordict). A run
that resumes reads a stage instead of running it only where the keys match; any other stage
runs again.
"""

from __future__ import annotations

import functools
import hashlib
import inspect
import re
import site
import sys
import sysconfig
import time
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import tensordict
import torch
import torchrl
from tensordict import TensorDictBase

import irc_torchrl
from irc_torchrl.algorithms.fit import FitResult
from irc_torchrl.checkpoint import read_weights, resolve_checkpoint
from irc_torchrl.config import config_to_dict
from irc_torchrl.data.files import remove_temporaries, write_text, write_torch
from irc_torchrl.envs.model import TaskModel

__all__ = ["AFTER_FITS", "Stages", "fit_settings", "format_resumed", "stage_key", "staged_by"]

#: the settings that act only once the fits are done (a check of them, how many datasets
#: calibrate their intervals and how the factors read their tails): a rerun that changes them
#: reuses the fits, and one with more calibration datasets the refits already done
AFTER_FITS = ("particles", "calibrate", "calibration_tail")
#: the address in an object's default repr
_ADDRESS = re.compile(r" at 0x[0-9a-fA-F]+")
#: how deep a task model's attributes are read into for the key
_DEPTH = 6


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
    """A digest of what a run's fits depend on: its ``settings`` (in full: a tensor by its
    bytes, not its shortened print), the policy's ``checkpoint`` (a file, or a packaged
    checkpoint's name), the task ``model`` (its class's source and its attributes), the
    recorded ``data`` in order, and the versions of the library's code, torch, torchrl and
    tensordict."""
    digest = hashlib.sha256()
    _digest_value(digest, "settings", dict(settings), set())
    digest.update(hashlib.sha256(resolve_checkpoint(checkpoint).read_bytes()).digest())
    if model is not None:
        _digest_model(digest, model)
    _digest_data(digest, data)
    versions = (torch.__version__, torchrl.__version__, tensordict.__version__)
    digest.update(f"{_code_digest()} {versions}".encode())
    return digest.hexdigest()


def _digest_model(digest: Any, model: TaskModel) -> None:
    """Feed a task model to ``digest``: its class, the source of its class and of the user
    code that class reads (a class defined in a notebook has none), and its attributes (what
    it was built with)."""
    task = type(model)
    digest.update(f"{task.__module__}.{task.__qualname__}".encode())
    for name, path in _user_sources(task).items():
        digest.update(name.encode())
        digest.update(path.read_bytes())
    _digest_value(digest, "model", model, set())


def _user_sources(task: type) -> dict[str, Path]:
    """The files of the user's own code a task class runs, by names that do not depend on
    where they lie (``unit/relative/path.py``), in order.

    A unit is a top-level package, every ``.py`` file under it whichever are imported, or a
    top-level module. The units are those of the task's class and its task base classes
    (wherever installed) and, transitively, those their modules use (the modules, functions
    and classes they hold), leaving out the standard library, other installed packages and
    this library (keyed by :func:`_code_digest`)."""
    paths = sysconfig.get_paths()
    stdlib = [paths["stdlib"], paths["platstdlib"]]
    installed = [paths["purelib"], paths["platlib"], *site.getsitepackages()]
    installed.append(site.getusersitepackages())
    classes = [cls for cls in task.__mro__ if issubclass(cls, TaskModel) and cls is not TaskModel]
    own = {cls.__module__.partition(".")[0] for cls in classes}
    units: dict[str, list[Path]] = {}
    walked: set[str] = set()
    pending = [sys.modules.get(cls.__module__) for cls in classes]
    while pending:
        module = pending.pop()
        if module is None or module.__name__ in walked:
            continue
        walked.add(module.__name__)
        unit = module.__name__.partition(".")[0]
        if unit not in units:
            roots = _unit_roots(unit)
            shared = stdlib if unit in own else [*stdlib, *installed]
            outside = unit == irc_torchrl.__name__ or any(_under(r, shared) for r in roots)
            units[unit] = [] if outside else roots
        if not units[unit]:
            continue
        for value in vars(module).values():
            if inspect.ismodule(value):
                pending.append(value)
            elif inspect.isclass(value) or inspect.isroutine(value):
                pending.append(sys.modules.get(getattr(value, "__module__", None) or ""))
    files = {}
    for unit, roots in units.items():
        for root in roots:
            if root.is_file():
                files[unit] = root
                continue
            for path in root.rglob("*.py"):
                files[f"{unit}/{path.relative_to(root).as_posix()}"] = path
    return dict(sorted(files.items()))


def _unit_roots(unit: str) -> list[Path]:
    """Where the top-level module or package ``unit`` lies: its file, or its folders (more than
    one for a namespace package); none for a module without a file (built in, a notebook's)."""
    top = sys.modules.get(unit)
    folders = getattr(top, "__path__", None)
    if folders is not None:
        return [Path(folder).resolve() for folder in folders if Path(folder).is_dir()]
    file = getattr(top, "__file__", None)
    return [Path(file).resolve()] if file and Path(file).is_file() else []


def _under(path: Path, roots: Iterable[str]) -> bool:
    """Whether ``path`` lies in one of the folders ``roots``."""
    return any(path.is_relative_to(Path(root).resolve()) for root in roots)


def _digest_value(digest: Any, name: str, value: Any, seen: set[int], depth: int = 0) -> None:
    """Feed ``value`` to ``digest`` in full: tensors and NumPy arrays by their bytes and
    containers and plain objects (a θ space, an action spec) by their contents, wherever they
    sit, so that no repr rounds a number away, hides a field or orders a set by the process's
    hash seed."""
    if isinstance(value, torch.Tensor):
        _digest_tensor(digest, name, value)
        return
    if isinstance(value, np.ndarray) and not value.dtype.hasobject:
        digest.update(f"{name}{value.dtype.descr}{list(value.shape)}".encode())
        digest.update(np.ascontiguousarray(value).tobytes())
        return
    plain = value is None or isinstance(value, (bool, int, float, complex, str, bytes))
    code = inspect.isroutine(value) or inspect.isclass(value) or inspect.ismodule(value)
    inner = _state(value) if hasattr(value, "__dict__") and not code else None
    if plain or depth > _DEPTH or id(value) in seen:
        items = None
    elif isinstance(value, Mapping):
        items = sorted(((str(k), v) for k, v in value.items()), key=lambda kv: kv[0])
    elif isinstance(value, (list, tuple)):
        items = [(str(i), v) for i, v in enumerate(value)]
    elif isinstance(value, np.ndarray):  # holding objects
        items = [(str(list(value.shape)), value.tolist())]
    elif isinstance(value, (set, frozenset)):
        items = [(str(i), v) for i, v in enumerate(sorted(value, key=_repr))]
    elif inner is not None:
        items = sorted(inner.items())
    else:
        items = None
    digest.update(f"{name}:{type(value).__qualname__}".encode())
    if items is None:  # an object's default repr names its address, no other process's
        digest.update(_ADDRESS.sub("", _repr(value)).encode())
        return
    seen.add(id(value))
    for key, item in items:
        _digest_value(digest, f"{name}.{key}", item, seen, depth + 1)


def _state(value: Any) -> dict:
    """An object's attributes as pickling keeps them (its ``__getstate__``, by default its
    ``vars``): what it drops there is a cache (a θ space's bounds), filled by its use, not by
    what it was built with."""
    try:
        state = value.__getstate__()
    except TypeError:  # an object that refuses pickling
        state = None
    return state if isinstance(state, dict) else vars(value)


def _repr(value: Any) -> str:
    """``repr(value)``, or its type's name where that repr raises (the key then reads less)."""
    try:
        return repr(value)
    except Exception:  # a user's object may raise anything
        return f"<{type(value).__qualname__}>"


def _digest_data(digest: Any, data: Iterable[TensorDictBase]) -> None:
    """Feed every tensor of ``data`` to ``digest``, in order, with its key, dtype and shape."""
    for trials in data:
        for key in sorted(trials.keys(True, True), key=str):
            _digest_tensor(digest, str(key), trials[key])


def _digest_tensor(digest: Any, name: str, value: torch.Tensor) -> None:
    """Feed one tensor's name, dtype, shape and bytes to ``digest``."""
    value = value.detach().cpu().contiguous()
    digest.update(f"{name}{value.dtype}{list(value.shape)}".encode())
    digest.update(value.reshape(-1).view(torch.uint8).numpy().tobytes())


@functools.cache
def _code_digest() -> str:
    """A digest of the library's own source (an edited install's stages are not reused)."""
    root = Path(irc_torchrl.__file__).parent
    digest = hashlib.sha256()
    for path in sorted(root.rglob("*.py")):
        digest.update(path.relative_to(root).as_posix().encode())
        digest.update(path.read_bytes())
    return digest.hexdigest()


#: the file in a stages folder naming the command whose stages it holds
COMMAND_FILE = "command"


def staged_by(folder: str | Path) -> str | None:
    """The command whose stages ``folder`` holds (``None``: none named, or no folder)."""
    try:
        return (Path(folder) / COMMAND_FILE).read_text().strip() or None
    except OSError:
        return None


class Stages:
    """The stages of one run in ``folder`` (``None``: none kept), under the run's ``key``.

    With ``resume``, a stage an earlier run of the same key finished is read instead of
    fitted (or checked); ``reused`` names those, in order. ``command`` (``irc fit``'s or
    ``recover``'s) is named in the folder beside the first stage saved, so that another
    command refuses the folder rather than prune an interrupted run's stages.
    """

    def __init__(
        self,
        folder: str | Path | None = None,
        key: str = "",
        resume: bool = False,
        command: str = "",
    ) -> None:
        self.folder = None if folder is None else Path(folder)
        self.key = key
        self.resume = resume
        self.command = command
        self.reused: list[str] = []

    def include(self, data: Iterable[TensorDictBase]) -> None:
        """Key the stages by ``data`` too: trials the run simulates itself, once simulated
        (they show any change of the task that its settings and source do not)."""
        digest = hashlib.sha256(self.key.encode())
        _digest_data(digest, data)
        self.key = digest.hexdigest()

    def fit(
        self, name: str, work: Callable[[], FitResult], device: torch.device | str = "cpu"
    ) -> tuple[FitResult, float]:
        """Stage ``name``'s fit and the seconds it took (an earlier run's, where read), on
        ``device``: ``work()``'s, saved once finished, or one kept by an earlier run."""

        def restore(state: Any) -> FitResult:
            return FitResult.from_state_dict(state).to(device)

        return self._stage(name, work, lambda r: r.cpu().state_dict(), restore)

    def check(
        self,
        name: str,
        work: Callable[[], dict[str, torch.Tensor]],
        device: torch.device | str = "cpu",
    ) -> tuple[dict[str, torch.Tensor], float]:
        """Stage ``name``'s check of a fit (tensors by name, as :func:`particle_check` gives
        them) and its seconds, kept and read as :meth:`fit` keeps and reads a fit."""

        def restore(state: Any) -> dict[str, torch.Tensor]:
            return {key: value.to(device) for key, value in _tensors(state).items()}

        return self._stage(name, work, lambda r: {k: r[k].cpu() for k in r}, restore)

    def _stage(
        self,
        name: str,
        work: Callable[[], Any],
        state: Callable[[Any], Any],
        restore: Callable[[Any], Any],
    ) -> tuple[Any, float]:
        """Stage ``name`` and its seconds: an earlier run's, ``restore``d from its kept state,
        where resuming finds it, else ``work()``'s, its ``state`` saved."""
        kept = self._read(name, restore) if self.resume else None
        if kept is not None:
            return kept
        begin = time.perf_counter()
        result = work()
        seconds = time.perf_counter() - begin
        if self.folder is not None:
            stage = {"key": self.key, "seconds": seconds, "result": state(result)}
            write_torch(self.folder / f"{name}.pt", stage)
            if self.command and staged_by(self.folder) != self.command:
                write_text(self.folder / COMMAND_FILE, self.command + "\n")
        return result, seconds

    def prune(self) -> None:
        """Remove the stages of other keys (another run's settings, an older library) and
        what a killed save left, so that those left belong to the run finished beside them."""
        if self.folder is None or not self.folder.is_dir():
            return
        for path in self.folder.glob("*.pt"):
            if self._load(path) is None:
                path.unlink()
        remove_temporaries(self.folder)

    def summarise(self, summary: dict) -> None:
        """Name the stages read (``summary["resumed"]``) in a resuming run's summary."""
        if self.resume:
            summary["resumed"] = self.reused

    def _read(self, name: str, restore: Callable[[Any], Any]) -> tuple[Any, float] | None:
        """Stage ``name`` of this key, ``restore``d, with its seconds, or ``None`` where none is
        kept (or it is unreadable); a stage read is named in :attr:`reused`."""
        if self.folder is None:
            return None
        stage = self._load(self.folder / f"{name}.pt")
        if stage is None:
            return None
        try:
            kept = restore(stage["result"]), float(stage["seconds"])
        except (KeyError, TypeError, ValueError):
            return None
        self.reused.append(name)
        return kept

    def _load(self, path: Path) -> dict | None:
        """The stage file ``path`` if it holds this key, else ``None``."""
        try:
            stage = read_weights(path)
        except ValueError:
            return None
        if not isinstance(stage, dict) or stage.get("key") != self.key:
            return None
        return stage


def _tensors(state: Any) -> dict[str, torch.Tensor]:
    """A check's kept ``state``, which must be tensors by name."""
    if not isinstance(state, Mapping) or not all(
        isinstance(k, str) and isinstance(v, torch.Tensor) for k, v in state.items()
    ):
        raise TypeError("a check's stage holds tensors by name")
    return dict(state)


def format_resumed(summary: Mapping[str, Any]) -> list[str]:
    """The line saying which stages (fits and checks) a resuming run read (none for a run that
    did not resume)."""
    if "resumed" not in summary:
        return []
    if not summary["resumed"]:
        return ["resumed: no fit of these settings was kept in the folder; every fit ran anew"]
    return [f"resumed: {', '.join(summary['resumed'])} read from the earlier run"]
