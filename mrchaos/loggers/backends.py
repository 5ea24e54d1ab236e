"""A run's loggers, picked by name: TorchRL's CSV, TensorBoard, W&B and MLflow loggers, and rerun.

    loggers = RunLoggers(["rerun", "tensorboard"], "full", "runs/full")
    loggers.log_scalar("reward", 0.5, step=1)

Each backend writes under the run folder: ``csv/`` (TorchRL's CSV logger, one file per
scalar), ``tensorboard/``, ``wandb/``, ``mlruns/`` and ``recording.rrd``. W&B and MLflow run
offline unless ``online`` is set: W&B writes an offline run to sync later
(``wandb sync runs/<name>/wandb/...``); MLflow's store is the local ``mlruns/`` folder, or
the server named by ``MLFLOW_TRACKING_URI`` when online.
"""

from __future__ import annotations

import importlib.util
import math
import os
from pathlib import Path
from typing import Any

from torchrl.record.loggers import Logger, get_logger

from mrchaos.core.errors import MrchaosError

__all__ = ["LOGGER_BACKENDS", "LoggerUnavailable", "RunLoggers", "check_backends"]

#: Backend names, and the package each needs (the ``[tensorboard]``, ``[wandb]``, ``[mlflow]`` extras).
LOGGER_BACKENDS: dict[str, str | None] = {
    "csv": None,
    "rerun": "rerun",
    "tensorboard": "tensorboard",
    "wandb": "wandb",
    "mlflow": "mlflow",
}


class LoggerUnavailable(MrchaosError, ImportError):
    """A logger backend whose package is not installed."""


def check_backends(backends: list[str]) -> None:
    """Raise ValueError naming the backends that :data:`LOGGER_BACKENDS` does not know."""
    unknown = [b for b in backends if b not in LOGGER_BACKENDS]
    if unknown:
        raise ValueError(f"logger.backends: unknown {unknown}; choose from {', '.join(LOGGER_BACKENDS)}")


class RunLoggers:
    """The loggers of one run, fanned out.

    Args:
        backends: names from :data:`LOGGER_BACKENDS`.
        name: the experiment's name.
        run_dir: the run folder; every backend writes below it.
        rerun_file: the rerun recording's file name (a resumed run writes a new one).
        online: W&B and MLflow talk to their servers instead of writing offline.
        project: the W&B project and MLflow experiment.
    """

    def __init__(
        self,
        backends: list[str],
        name: str,
        run_dir: str | Path,
        rerun_file: str = "recording.rrd",
        online: bool = False,
        project: str = "mrchaos",
    ) -> None:
        check_backends(backends)
        for b in backends:
            pkg = LOGGER_BACKENDS[b]
            if pkg is not None and importlib.util.find_spec(pkg) is None:
                raise LoggerUnavailable(f"logger.backends: '{b}' needs the {pkg} package: pip install -e '.[{b}]'")
        run_dir = Path(run_dir)
        self.loggers: dict[str, Logger] = {}
        for b in dict.fromkeys(backends):
            self.loggers[b] = self._make(b, name, run_dir, rerun_file, online, project)

    @staticmethod
    def _make(backend: str, name: str, run_dir: Path, rerun_file: str, online: bool, project: str) -> Logger:
        if backend == "rerun":
            from mrchaos.loggers.rerun_logger import RerunLogger

            return RerunLogger(name, str(run_dir), file_name=rerun_file)
        if backend == "wandb":
            (run_dir / "wandb").mkdir(parents=True, exist_ok=True)
            return get_logger(
                "wandb",
                str(run_dir),
                name,
                wandb_kwargs={"offline": not online, "project": project, "save_dir": str(run_dir)},
            )
        if backend == "mlflow":
            uri = os.environ.get("MLFLOW_TRACKING_URI") if online else None
            if online and not uri:
                raise ValueError("logger.online with mlflow needs MLFLOW_TRACKING_URI set to the server")
            if uri:
                from torchrl.record.loggers.mlflow import MLFlowLogger

                return MLFlowLogger(name, tracking_uri=uri)
            return get_logger("mlflow", str(run_dir / "mlruns"), name)
        # csv and tensorboard write to <log_dir>/<exp_name>: the run folder's own subfolder.
        return get_logger(backend, str(run_dir), backend)

    def __contains__(self, backend: str) -> bool:
        return backend in self.loggers

    def get(self, backend: str) -> Logger | None:
        """The logger of one backend, if the run has it."""
        return self.loggers.get(backend)

    def log_scalar(self, name: str, value: float | None, step: int) -> None:
        """One scalar to every backend (None and NaNs, which some backends reject, are skipped)."""
        if value is None or (isinstance(value, float) and math.isnan(value)):
            return
        for lg in self.loggers.values():
            lg.log_scalar(name, float(value), step=step)

    def log_hparams(self, cfg: dict[str, Any]) -> None:
        """The resolved config, flattened to dotted keys where a backend wants flat values."""
        flat = _flatten(cfg)
        for b, lg in self.loggers.items():
            lg.log_hparams(cfg if b == "rerun" else flat)

    def log_text(self, name: str, text: str, step: int) -> None:
        """An event line (rerun only: the other backends have no text timeline worth it)."""
        rr = self.loggers.get("rerun")
        if rr is not None:
            rr.log_text(name, text, step=step)

    def close(self) -> None:
        """Flush and close every backend."""
        for lg in self.loggers.values():
            lg.shutdown()


def _flatten(d: dict, prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(_flatten(v, key + "."))
        else:
            out[key] = v if isinstance(v, (int, float, str, bool)) else str(v)
    return out
