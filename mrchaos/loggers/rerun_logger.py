"""``RerunLogger``: a TorchRL logger that writes a rerun ``.rrd`` recording.

Scalars go to ``scalars/<name>`` on the ``iteration`` timeline; observation
images and chosen actions of a few worlds go to ``worlds/<i>/...``. Open the file
with ``rerun runs/<name>/recording.rrd``.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import rerun as rr
from torchrl.record.loggers import Logger

__all__ = ["RerunLogger", "EpisodeRecorder"]


class RerunLogger(Logger):
    """Logs to ``<log_dir>/<file_name>`` through its own ``rerun.RecordingStream``.

    A resumed run writes a new file with the same recording id, and rerun merges
    files of one recording when opened together.
    """

    def __init__(self, exp_name: str, log_dir: str, file_name: str = "recording.rrd") -> None:
        self.file_name = file_name
        super().__init__(exp_name=exp_name, log_dir=log_dir)

    def _create_experiment(self) -> rr.RecordingStream:
        Path(self.log_dir).mkdir(parents=True, exist_ok=True)
        stream = rr.RecordingStream("mrchaos", recording_id=self.exp_name)
        stream.save(str(Path(self.log_dir) / self.file_name))
        return stream

    def shutdown(self, timeout: float | None = None) -> None:
        """Flush and close the file, so it is complete (footer included) before the process ends."""
        if not self._service_shutdown:
            self.experiment.flush()
            self.experiment.disconnect()
        super().shutdown(timeout)

    def log_scalar(self, name: str, value: float, step: int | None = None) -> None:
        if step is not None:
            rr.set_time("iteration", sequence=int(step), recording=self.experiment)
        rr.log(f"scalars/{name}", rr.Scalars(float(value)), recording=self.experiment)

    def log_video(self, name: str, video, step: int | None = None, **kwargs) -> None:
        frames = np.asarray(video)
        for t, frame in enumerate(frames):
            rr.set_time("frame", sequence=t, recording=self.experiment)
            rr.log(name, rr.Image(frame), recording=self.experiment)

    def log_hparams(self, cfg) -> None:
        import yaml

        text = yaml.safe_dump(cfg if isinstance(cfg, dict) else dict(cfg), sort_keys=False)
        rr.log("config", rr.TextDocument(text, media_type="text/markdown"), static=True, recording=self.experiment)

    def log_histogram(self, name: str, data: Sequence, **kwargs) -> None:
        counts, _ = np.histogram(np.asarray(data), bins=kwargs.get("bins", 32))
        rr.log(name, rr.BarChart(counts), recording=self.experiment)

    def log_text(self, name: str, text: str, step: int | None = None) -> None:
        """A text event (e.g. the curriculum switch) on the iteration timeline."""
        if step is not None:
            rr.set_time("iteration", sequence=int(step), recording=self.experiment)
        rr.log(name, rr.TextLog(text), recording=self.experiment)

    def log_worlds(
        self,
        step: int,
        observations: np.ndarray,
        actions: np.ndarray,
        rewards: np.ndarray,
        grid_xy: tuple[np.ndarray, np.ndarray],
        extent: float,
    ) -> None:
        """Silhouette, view and chosen placement of a few worlds: observations (W, 2, H, W) uint8,
        actions (W, 3) grid indices, rewards (W,)."""
        rr.set_time("iteration", sequence=int(step), recording=self.experiment)
        size = observations.shape[-1]
        for i, (obs, act, rew) in enumerate(zip(observations, actions, rewards, strict=True)):
            base = f"worlds/{i}"
            rr.log(f"{base}/silhouette", rr.Image(obs[0]), recording=self.experiment)
            rr.log(f"{base}/view", rr.Image(obs[1]), recording=self.experiment)
            x, y = grid_xy[0][act[0]], grid_xy[1][act[1]]
            px = (x + extent / 2) / extent * size
            py = (extent / 2 - y) / extent * size
            rr.log(
                f"{base}/view/action",
                rr.Points2D([[px, py]], radii=2.0, labels=[f"θ#{int(act[2])}"]),
                recording=self.experiment,
            )
            rr.log(f"{base}/reward", rr.Scalars(float(rew)), recording=self.experiment)


class EpisodeRecorder:
    """Step-by-step rerun recording of evaluation episodes (``mrchaos-bench --record``).

    Entities ``<policy>/<family>/<episode id>/{silhouette,view,action,coverage/<piece>}``
    on the ``step`` timeline.
    """

    def __init__(self, path: str | Path, piece_names: Sequence[str], grid_xy, extent: float) -> None:
        self.stream = rr.RecordingStream("mrchaos-bench")
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        self.stream.save(str(path))
        self.piece_names = list(piece_names)
        self.grid_xy = grid_xy
        self.extent = extent
        self._scene_frames: dict[str, int] = {}

    def log_episodes(
        self, policy: str, family: str, ids: Sequence[str], res, piece_names: Sequence[str] | None = None
    ) -> None:
        """Every recorded step of ``res``; ``piece_names`` when the episodes' piece set is not
        the recorder's (a family may mix piece sets, e.g. 3 to 6 soda cans)."""
        names = list(piece_names) if piece_names is not None else self.piece_names
        for rec in res.steps or []:
            rr.set_time("step", sequence=int(rec["t"]), recording=self.stream)
            for k, ep in enumerate(rec["episode"]):
                base = f"{policy}/{family}/{ids[ep]}"
                obs = rec["observation"][k]
                size = obs.shape[-1]
                rr.log(f"{base}/silhouette", rr.Image(obs[0]), recording=self.stream)
                rr.log(f"{base}/view", rr.Image(obs[1]), recording=self.stream)
                a = rec["action"][k]
                x, y = self.grid_xy[0][a[0]], self.grid_xy[1][a[1]]
                px, py = (x + self.extent / 2) / self.extent * size, (self.extent / 2 - y) / self.extent * size
                rr.log(
                    f"{base}/view/action",
                    rr.Points2D([[px, py]], radii=2.0, labels=[f"{names[rec['t']]} θ#{int(a[2])}"]),
                    recording=self.stream,
                )
                for i, name in enumerate(names):
                    rr.log(f"{base}/coverage/{name}", rr.Scalars(float(rec["coverage"][k][i])), recording=self.stream)
                rr.log(f"{base}/reward", rr.Scalars(float(rec["reward"][k])), recording=self.stream)

    def log_scene(self, policy: str, family: str, episode_id: str, step: int, frames: Sequence[np.ndarray]) -> None:
        """Rendered frames of the robot placing the piece of ``step`` (``<episode>/scene`` on the
        ``step`` timeline, and on ``scene_frame``, which counts frames through the episode)."""
        base = f"{policy}/{family}/{episode_id}/scene"
        k0 = self._scene_frames.get(base, 0)
        for k, frame in enumerate(frames):
            rr.set_time("step", sequence=int(step), recording=self.stream)
            rr.set_time("scene_frame", sequence=k0 + k, recording=self.stream)
            rr.log(base, rr.Image(frame).compress(jpeg_quality=85), recording=self.stream)
        self._scene_frames[base] = k0 + len(frames)
        rr.reset_time(recording=self.stream)

    def close(self) -> None:
        """Flush and close the file."""
        self.stream.flush()
        self.stream.disconnect()
