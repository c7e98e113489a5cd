"""Shared utilities of the training scripts: the multi-agent SB3 VecEnv and the SB3 logger set-up (exported
here), and the modules the scripts import by name: the collector that drives the cars (``utils.collector``), the run
plumbing (``utils.run``) and checkpoints (``utils.checkpoint``)."""

from utils.logger import configure_logger, hyperparameter_table, log_image, log_video, make_run_name
from utils.vec_env import ENV_IDS, EnvFactory, MultiAgentVecEnv, make_vec_env

__all__ = [
    "ENV_IDS",
    "EnvFactory",
    "MultiAgentVecEnv",
    "configure_logger",
    "hyperparameter_table",
    "log_image",
    "log_video",
    "make_run_name",
    "make_vec_env",
]
