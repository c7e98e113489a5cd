"""Shared utilities of the training scripts: the multi-agent SB3 VecEnv and the SB3 logger set-up."""

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
