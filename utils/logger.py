"""Run names, Stable-Baselines3 logger set-up, hyperparameter table, videos and images in TensorBoard.

All TensorBoard output goes through SB3's own logger (``stable_baselines3.common.logger``): scalars
with ``logger.record(...)`` + ``logger.dump(step)`` as usual, and the helpers here for the rest.

The hyperparameter table, videos and images are written straight to the logger's TensorBoard output
format(s) (``TensorBoardOutputFormat.write`` with SB3's ``str`` / ``Video`` / ``Image`` values), not
through ``logger.record``: recorded values are only written at the next ``logger.dump`` and for every
format, so the CSV would get an empty row per video and stdout a warning, and the step would be the
dump's rather than the one given here. Going to the TensorBoard format directly leaves the values
recorded for the current iteration untouched.

Videos: ``torch.utils.tensorboard``'s ``add_video`` encodes the GIF with ``moviepy.editor`` and, if
that import fails (moviepy 2 removed the module), prints a line and logs nothing. So
:func:`configure_logger` checks the import up front (:func:`check_video_support`) and fails loudly.
"""

from __future__ import annotations

import os
import time
import warnings
from collections.abc import Iterable, Mapping
from typing import Any

import numpy as np
import torch as th
from stable_baselines3.common.logger import CSVOutputFormat, Image, Logger, TensorBoardOutputFormat, Video, configure

#: Tag of the hyperparameter table in TensorBoard's text tab.
HYPERPARAMETERS_TAG = "hyperparameters"


def make_run_name(env_id: str, exp_name: str, seed: int) -> str:
    """CleanRL-style run name ``{env_id}__{exp_name}__{seed}__{unix time}``."""
    return f"{env_id}__{exp_name}__{seed}__{int(time.time())}"


def hyperparameter_table(hyperparameters: Mapping[str, Any]) -> str:
    """Markdown table with one ``|param|value|`` row per hyperparameter (in the mapping's order).

    ``|`` in keys or values is escaped and newlines become spaces, so every entry stays one row.
    """

    def cell(x: Any) -> str:
        return str(x).replace("|", "\\|").replace("\n", " ")

    rows = "\n".join(f"|{cell(key)}|{cell(value)}|" for key, value in hyperparameters.items())
    return "|param|value|\n|-|-|\n" + rows


def check_video_support() -> None:
    """Raise ``ImportError`` unless ``torch.utils.tensorboard`` can encode videos (needs ``moviepy.editor``).

    Importing ``moviepy.editor`` runs ``pygame.init()``; ``SDL_AUDIODRIVER`` defaults to ``"dummy"``
    here so that this does not probe sound cards, and ``SDL_NO_SIGNAL_HANDLERS`` to ``"1"``: SDL would
    otherwise turn SIGINT and SIGTERM into quit events nobody reads, and a training run would survive
    Ctrl-C and ``kill``. On a machine with no display (neither ``DISPLAY`` nor ``WAYLAND_DISPLAY``),
    ``SDL_VIDEODRIVER`` defaults to ``"offscreen"``, the driver SDL falls back to there anyway: probing
    Wayland first is what printed "error: XDG_RUNTIME_DIR is invalid or not set" on every run.
    (Not ``"dummy"``: highway-env renders black frames with it.)
    """
    os.environ.setdefault("SDL_AUDIODRIVER", "dummy")
    os.environ.setdefault("SDL_NO_SIGNAL_HANDLERS", "1")
    os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")
    if not os.environ.get("DISPLAY") and not os.environ.get("WAYLAND_DISPLAY"):
        os.environ.setdefault("SDL_VIDEODRIVER", "offscreen")
    try:
        from moviepy import editor  # noqa: F401
    except ImportError as exc:
        raise ImportError(
            "TensorBoard videos need `moviepy.editor` (moviepy < 2; requirements.txt pins moviepy==1.0.3). "
            "Without it SummaryWriter.add_video silently logs nothing."
        ) from exc


def tensorboard_formats(logger: Logger) -> list[TensorBoardOutputFormat]:
    """The TensorBoard output formats of an SB3 logger (their ``.writer`` is a ``SummaryWriter``)."""
    return [f for f in logger.output_formats if isinstance(f, TensorBoardOutputFormat)]


def _write_tensorboard(logger: Logger, tag: str, value: Any, step: int) -> int:
    formats = tensorboard_formats(logger)
    if not formats:
        warnings.warn(f"{tag!r} not logged: the logger has no 'tensorboard' output format")
    for fmt in formats:
        fmt.write({tag: value}, {tag: None}, step)
    return len(formats)


def configure_logger(
    run_dir: str,
    hyperparameters: Mapping[str, Any] | None = None,
    formats: Iterable[str] = ("stdout", "csv", "tensorboard"),
    check_videos: bool = True,
) -> Logger:
    """An SB3 logger writing to ``run_dir`` (``stable_baselines3.common.logger.configure``).

    :param run_dir: log directory, e.g. ``runs/<run_name>`` (created if needed; TensorBoard event
        file and ``progress.csv`` go there)
    :param hyperparameters: written as a markdown table (:func:`hyperparameter_table`) to TensorBoard's
        text tab under the tag ``"hyperparameters"`` at step 0
    :param formats: SB3 output formats ("stdout", "csv", "tensorboard", "log", "json")
    :param check_videos: with a "tensorboard" format, fail now (:func:`check_video_support`) rather
        than lose every video of the run
    """
    formats = list(formats)
    if check_videos and "tensorboard" in formats:
        check_video_support()
    csv_path = os.path.join(str(run_dir), "progress.csv")
    # A resumed run: SB3 truncates progress.csv, so its rows are put back and appended to. Until they are back on
    # disk they live in progress.csv.resume (a rename, atomic), which a kill in between leaves for the next resume.
    # A progress.csv at least as long as such a backup is newer (the kill came after the rows were back): it is kept.
    backup, previous_rows = csv_path + ".resume", ""
    if "csv" in formats:
        if os.path.exists(csv_path) and os.path.exists(backup):
            if os.path.getsize(csv_path) >= os.path.getsize(backup):
                os.remove(backup)
        if os.path.exists(csv_path) and not os.path.exists(backup):
            os.replace(csv_path, backup)
        if os.path.exists(backup):
            with open(backup) as f:
                previous_rows = f.read()
    logger = configure(str(run_dir), formats)
    if previous_rows:
        for fmt in logger.output_formats:
            if isinstance(fmt, CSVOutputFormat):
                fmt.file.write(previous_rows)
                fmt.file.flush()
                os.fsync(fmt.file.fileno())
                fmt.keys = previous_rows.splitlines()[0].split(fmt.separator)
    if "csv" in formats and os.path.exists(backup):
        os.remove(backup)
    if hyperparameters:
        _write_tensorboard(logger, HYPERPARAMETERS_TAG, hyperparameter_table(hyperparameters), 0)
    return logger


def log_video(logger: Logger, tag: str, frames: np.ndarray, step: int, fps: float = 30) -> int:
    """Write a video (a GIF image summary) to the logger's TensorBoard output.

    :param frames: ``(T, H, W, 3)`` uint8 RGB frames, ``T >= 1``
    :param step: global step of the summary
    :param fps: frames per second of the GIF
    :return: the number of TensorBoard writers written to (0 with a warning if there is none)
    :raises ValueError: for a wrong shape, dtype or fps
    """
    frames = np.asarray(frames)
    if frames.ndim != 4 or frames.shape[-1] != 3 or frames.shape[0] < 1:
        raise ValueError(f"video frames must have shape (T, H, W, 3) with T >= 1, got {frames.shape}")
    if frames.dtype != np.uint8:
        raise ValueError(f"video frames must be uint8, got {frames.dtype}")
    if not fps > 0:
        raise ValueError(f"fps must be positive, got {fps}")
    video = th.from_numpy(np.ascontiguousarray(frames.transpose(0, 3, 1, 2)))[None]  # (N=1, T, C, H, W)
    return _write_tensorboard(logger, tag, Video(video, fps), step)


def log_image(logger: Logger, tag: str, image: np.ndarray, step: int) -> int:
    """Write an image to the logger's TensorBoard output.

    :param image: ``(H, W, 3)`` uint8 RGB image
    :return: the number of TensorBoard writers written to (0 with a warning if there is none)
    :raises ValueError: for a wrong shape or dtype
    """
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[-1] != 3:
        raise ValueError(f"image must have shape (H, W, 3), got {image.shape}")
    if image.dtype != np.uint8:
        raise ValueError(f"image must be uint8, got {image.dtype}")
    return _write_tensorboard(logger, tag, Image(np.ascontiguousarray(image.transpose(2, 0, 1)), "CHW"), step)
