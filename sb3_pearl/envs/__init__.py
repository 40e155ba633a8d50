"""Task families (Gymnasium envs with the ``set_task`` hook), registered on ``import sb3_pearl``.

Each family lives in its own module; :data:`FAMILIES` maps the registered id to its entry point
and time limit. ``register_envs()`` is idempotent.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym

from sb3_pearl.envs.task_protocol import MetaTaskEnv, Task, TaskFamily

# id -> (entry point, registration kwargs)
FAMILIES: dict[str, tuple[str, dict[str, Any]]] = {
    "PointGoalMeta-v0": ("sb3_pearl.envs.point_goal:PointGoalMetaEnv", {"max_episode_steps": 20}),
    "SafePointGoalMeta-v0": ("sb3_pearl.envs.safe_point_goal:SafePointGoalMetaEnv", {"max_episode_steps": 30}),
    "SparsePointGoalMeta-v0": ("sb3_pearl.envs.sparse_point_goal:SparsePointGoalMetaEnv", {"max_episode_steps": 20}),
    "PointMazeGoalMeta-v0": ("sb3_pearl.envs.point_maze_goal:PointMazeGoalMetaEnv", {"max_episode_steps": 300}),
    "HalfCheetahVelMeta-v0": ("sb3_pearl.envs.half_cheetah_vel:HalfCheetahVelMetaEnv", {"max_episode_steps": 200}),
    "Walker2dVelMeta-v0": ("sb3_pearl.envs.walker2d_vel:Walker2dVelMetaEnv", {"max_episode_steps": 200}),
    "AntVelMeta-v0": ("sb3_pearl.envs.ant_vel:AntVelMetaEnv", {"max_episode_steps": 200}),
    "AntDirMeta-v0": ("sb3_pearl.envs.ant_dir:AntDirMetaEnv", {"max_episode_steps": 200}),
    "AntGoalMeta-v0": ("sb3_pearl.envs.ant_goal:AntGoalMetaEnv", {"max_episode_steps": 200}),
    "HighwayMergeMeta-v0": ("sb3_pearl.envs.highway_merge:HighwayMergeMetaEnv", {"max_episode_steps": 60}),
}


def register_envs() -> None:
    """Register every task family with Gymnasium (safe to call more than once)."""
    for env_id, (entry_point, kwargs) in FAMILIES.items():
        if env_id not in gym.registry:
            gym.register(id=env_id, entry_point=entry_point, **kwargs)


__all__ = ["FAMILIES", "MetaTaskEnv", "Task", "TaskFamily", "register_envs"]
