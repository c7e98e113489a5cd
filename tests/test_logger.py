"""utils.logger: what reaches the TensorBoard event file and the CSV, read back from disk."""

from __future__ import annotations

import csv
import io
import os
import re
import sys
import time

import numpy as np
import pytest
from PIL import Image as PILImage
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
from tensorboard.plugins.text import metadata as text_metadata

from utils.logger import (
    check_video_support,
    configure_logger,
    hyperparameter_table,
    log_image,
    log_video,
    make_run_name,
    tensorboard_formats,
)

# Solid colours survive GIF palette quantisation exactly.
COLOURS = [(255, 0, 0), (0, 255, 0), (0, 0, 255), (255, 255, 255), (0, 0, 0)]


def read_events(run_dir) -> EventAccumulator:
    accumulator = EventAccumulator(str(run_dir), size_guidance={"scalars": 0, "images": 0, "tensors": 0})
    accumulator.Reload()
    return accumulator


def test_make_run_name_is_cleanrl_style():
    before = int(time.time())
    name = make_run_name("multi_car_racing", "dreamer_lstm", 3)
    match = re.fullmatch(r"multi_car_racing__dreamer_lstm__3__(\d+)", name)
    assert match and before <= int(match.group(1)) <= time.time()


def test_hyperparameter_table_is_markdown_with_escaped_cells():
    table = hyperparameter_table({"lr": 6e-4, "note": "a|b\nc"})
    assert table.splitlines() == ["|param|value|", "|-|-|", "|lr|0.0006|", "|note|a\\|b c|"]


def test_scalars_text_video_and_image_land_in_the_event_file(tmp_path):
    hyperparameters = {"seed": 1, "model_lr": 0.0006, "env_id": "multi_car_racing"}
    logger = configure_logger(str(tmp_path), hyperparameters, formats=("csv", "tensorboard"))
    assert len(tensorboard_formats(logger)) == 1

    for step in (10, 20):
        logger.record("charts/episodic_return", float(step) / 2)
        logger.record("losses/actor", -1.0)
        if step == 20:  # a video between record() and dump() must not disturb the pending values
            frames = np.zeros((5, 16, 24, 3), np.uint8)
            for t, colour in enumerate(COLOURS):
                frames[t] = colour
            assert log_video(logger, "videos/episode", frames, step=step, fps=10) == 1
        logger.dump(step)
    image = np.random.default_rng(0).integers(0, 256, (12, 20, 3), dtype=np.uint8)
    assert log_image(logger, "images/reconstruction", image, step=30) == 1
    logger.close()

    events = read_events(tmp_path)
    returns = events.Scalars("charts/episodic_return")
    assert [(e.step, e.value) for e in returns] == [(10, 5.0), (20, 10.0)]

    # Hyperparameters: a markdown table in TensorBoard's text plugin, at step 0.
    (text_event,) = events.Tensors(f"hyperparameters/{text_metadata.PLUGIN_NAME}_summary")
    assert text_event.step == 0
    text = text_event.tensor_proto.string_val[0].decode()
    assert text.splitlines() == ["|param|value|", "|-|-|", "|seed|1|", "|model_lr|0.0006|", "|env_id|multi_car_racing|"]

    # Video: an animated GIF image summary with every frame.
    (video,) = events.Images("videos/episode")
    assert video.step == 20 and (video.width, video.height) == (24, 16)
    gif = PILImage.open(io.BytesIO(video.encoded_image_string))
    assert gif.format == "GIF" and gif.n_frames == 5
    for t, colour in enumerate(COLOURS):
        gif.seek(t)
        assert np.all(np.asarray(gif.convert("RGB")) == colour), t

    # Image: lossless PNG, pixel for pixel.
    (png,) = events.Images("images/reconstruction")
    assert png.step == 30
    np.testing.assert_array_equal(np.asarray(PILImage.open(io.BytesIO(png.encoded_image_string)).convert("RGB")), image)

    # The CSV has exactly the two scalar rows: no rows for the text, video or image.
    with open(tmp_path / "progress.csv") as f:
        rows = list(csv.DictReader(f))
    assert [float(r["charts/episodic_return"]) for r in rows] == [5.0, 10.0]
    assert set(rows[0]) == {"charts/episodic_return", "losses/actor"}


def test_bad_video_and_image_inputs_raise_value_errors(tmp_path):
    logger = configure_logger(str(tmp_path), None, formats=("tensorboard",))
    with pytest.raises(ValueError, match=r"\(T, H, W, 3\)"):
        log_video(logger, "v", np.zeros((16, 16, 3), np.uint8), step=0)
    with pytest.raises(ValueError, match=r"\(T, H, W, 3\)"):
        log_video(logger, "v", np.zeros((2, 3, 16, 16), np.uint8), step=0)  # channels first
    with pytest.raises(ValueError, match="uint8"):
        log_video(logger, "v", np.zeros((2, 16, 16, 3), np.float32), step=0)
    with pytest.raises(ValueError, match="fps"):
        log_video(logger, "v", np.zeros((2, 16, 16, 3), np.uint8), step=0, fps=0)
    with pytest.raises(ValueError, match=r"\(H, W, 3\)"):
        log_image(logger, "i", np.zeros((16, 16), np.uint8), step=0)
    with pytest.raises(ValueError, match="uint8"):
        log_image(logger, "i", np.zeros((16, 16, 3), np.float64), step=0)
    logger.close()


def test_logging_a_video_without_tensorboard_warns(tmp_path):
    with pytest.warns(UserWarning, match="'hyperparameters' not logged"):
        logger = configure_logger(str(tmp_path), {"a": 1}, formats=("csv",))
    with pytest.warns(UserWarning, match="no 'tensorboard' output format"):
        assert log_video(logger, "v", np.zeros((2, 8, 8, 3), np.uint8), step=0) == 0
    logger.close()


def test_missing_moviepy_editor_fails_loudly(tmp_path, monkeypatch):
    """torch's add_video would silently log nothing; configure_logger must refuse instead."""
    import moviepy

    monkeypatch.delattr(moviepy, "editor", raising=False)
    monkeypatch.setitem(sys.modules, "moviepy.editor", None)  # as with moviepy 2, which removed it
    with pytest.raises(ImportError, match="moviepy"):
        check_video_support()
    with pytest.raises(ImportError, match="moviepy"):
        configure_logger(str(tmp_path), {"a": 1}, formats=("tensorboard",))
    configure_logger(str(tmp_path), {"a": 1}, formats=("tensorboard",), check_videos=False).close()


def test_resumed_run_keeps_its_csv_rows(tmp_path):
    """SB3's CSV writer truncates progress.csv; a resumed run must keep the earlier rows."""
    import csv

    from utils.logger import configure_logger

    for step, value in ((1, 1.0), (2, 2.0)):
        logger = configure_logger(tmp_path, formats=("csv",))
        logger.record("charts/a", value)
        if step == 2:
            logger.record("charts/b", 5.0)  # a new column after resuming
        logger.dump(step)
        logger.close()
    with open(tmp_path / "progress.csv") as f:
        rows = list(csv.DictReader(f))
    assert [r["charts/a"] for r in rows] == ["1.0", "2.0"]
    assert [r["charts/b"] for r in rows] == ["", "5.0"]


def test_a_kill_while_a_resume_restores_progress_csv_loses_no_row(tmp_path, monkeypatch):
    """SB3 truncates progress.csv when the logger is built; a kill before the rows are back must not lose them."""
    import utils.logger as logger_module

    logger = logger_module.configure_logger(tmp_path, formats=("csv",))
    for step in (1, 2):
        logger.record("charts/a", float(step))
        logger.dump(step)
    logger.close()
    whole = (tmp_path / "progress.csv").read_text()
    real_configure = logger_module.configure

    def killed(*args, **kwargs):  # the truncating logger is built, then the process dies
        real_configure(*args, **kwargs).close()
        raise KeyboardInterrupt

    monkeypatch.setattr(logger_module, "configure", killed)
    with pytest.raises(KeyboardInterrupt):
        logger_module.configure_logger(tmp_path, formats=("csv",))
    assert (tmp_path / "progress.csv").read_text() == ""  # SB3 truncated it: the rows are in the backup alone
    monkeypatch.setattr(logger_module, "configure", real_configure)
    logger = logger_module.configure_logger(tmp_path, formats=("csv",))  # the next resume
    logger.record("charts/a", 3.0)
    logger.dump(3)
    logger.close()
    assert (tmp_path / "progress.csv").read_text() == whole + "3.0\n"
    assert sorted(os.listdir(tmp_path)) == ["progress.csv"]  # the backup is gone once the rows are back
    # a backup beside a longer progress.csv (a kill after the rows were back, then rows logged by code that does not
    # know the backup): the progress.csv is the newer one and is kept
    (tmp_path / "progress.csv.resume").write_text(whole)
    logger = logger_module.configure_logger(tmp_path, formats=("csv",))
    logger.close()
    assert (tmp_path / "progress.csv").read_text() == whole + "3.0\n"
    assert sorted(os.listdir(tmp_path)) == ["progress.csv"]
