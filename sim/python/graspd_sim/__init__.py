"""graspd's tool-use tasks (Place mug, Position drill, Drive nail) for a trainer in Python.

    import numpy as np
    from graspd_sim import VecEnv

    env = VecEnv("place", instances="train", num_envs=16, seed=0)
    obs = env.reset()                                     # (16, obs_len) float32
    for _ in range(300):
        actions = policy(obs)                             # (16, act_len): wrist deltas, joint targets
        obs, rewards, terminated, truncated, info = env.step(actions)

The environments are graspd's MuJoCo simulator (graspd_sim::env::VecTaskEnv,
Rust) stepped in parallel in this process through its C ABI
(sim/ffi, ``libgraspd_sim_ffi.so``): no daemon and no copies through Python
objects (the observation, reward and flag arrays are NumPy views of the
simulator's own buffers, refreshed in place by every step; copy what you
keep). Episodes last 10 s (300 steps at 30 Hz) and end by time alone:
``truncated`` is set, ``terminated`` never; a finished environment is reset
at once with the next seed (Gymnasium's vector-env convention), its last
observation in ``info["final_observation"]``. Layouts, units and frames:
``env.observation_layout`` / ``env.action_layout`` and sim/src/obs.rs.

The library is looked for in $GRASPD_SIM_LIB, else in the workspace's
target/release (``cargo build --release -p graspd-sim-ffi``).
"""

import ctypes
import json
import os
from pathlib import Path

import numpy as np

__all__ = ["VecEnv", "SimError", "library_path"]


class SimError(RuntimeError):
    """A refused configuration or action, or a failure inside the simulator."""


def library_path():
    env = os.environ.get("GRASPD_SIM_LIB")
    if env:
        return Path(env)
    return Path(__file__).resolve().parents[3] / "target" / "release" / "libgraspd_sim_ffi.so"


_LIB = None


def _lib():
    global _LIB
    if _LIB is None:
        path = library_path()
        if not path.exists():
            raise SimError(f"{path} not found: cargo build --release -p graspd-sim-ffi, or set GRASPD_SIM_LIB")
        lib = ctypes.CDLL(str(path))
        h = ctypes.c_void_p
        f32p, u8p = ctypes.POINTER(ctypes.c_float), ctypes.POINTER(ctypes.c_uint8)
        sigs = {
            "graspd_env_last_error": ([], ctypes.c_char_p),
            "graspd_env_new": ([ctypes.c_char_p], h),
            "graspd_env_free": ([h], None),
            "graspd_env_info": ([h], ctypes.c_char_p),
            "graspd_env_reset": ([h, ctypes.c_uint64], ctypes.c_int32),
            "graspd_env_step": ([h, f32p, ctypes.c_size_t], ctypes.c_int32),
            "graspd_env_expert_actions": ([h, f32p, ctypes.c_size_t], ctypes.c_int32),
            "graspd_env_observations": ([h], f32p),
            "graspd_env_final_observations": ([h], f32p),
            "graspd_env_rewards": ([h], f32p),
            "graspd_env_dones": ([h], u8p),
            "graspd_env_successes": ([h], u8p),
            "graspd_env_drain_finished": ([h], ctypes.c_char_p),
        }
        for name, (args, res) in sigs.items():
            fn = getattr(lib, name)
            fn.argtypes, fn.restype = args, res
        _LIB = lib
    return _LIB


def _error():
    return SimError((_lib().graspd_env_last_error() or b"").decode("utf-8", errors="replace"))


class VecEnv:
    """N environments of one task, dealt round the chosen tools (module docs).

    ``instances``: "canonical", "train", "all" (canonical and train), "test"
    (with ``grasp_from="register"``), a tool's name or a list of those.
    ``grasp_from``: "inprocess" (the tool's training latent) or "register"
    (the scene camera's view registered as the daemon does). ``start``:
    "pregrasp", "canonical" (w/o GG) or "neutral" (w/o PG).
    """

    def __init__(self, task, instances="all", num_envs=16, threads=0, seed=0, grasp_from="inprocess",
                 start="pregrasp"):
        config = {"task": task, "instances": instances, "envs": num_envs, "threads": threads, "seed": seed,
                  "grasp_from": grasp_from, "start": start}
        lib = _lib()
        self._h = lib.graspd_env_new(json.dumps(config).encode())
        if not self._h:
            raise _error()
        self.info = json.loads(lib.graspd_env_info(self._h))
        self.num_envs = self.info["envs"]
        self.observation_len = self.info["observation_len"]
        self.action_len = self.info["action_len"]
        self.observation_layout = {s["name"]: slice(s["offset"], s["offset"] + s["len"])
                                   for s in self.info["observation_layout"]}
        self.action_layout = {s["name"]: slice(s["offset"], s["offset"] + s["len"])
                              for s in self.info["action_layout"]}
        n, o = self.num_envs, self.observation_len
        view = np.ctypeslib.as_array
        self._obs = view(lib.graspd_env_observations(self._h), shape=(n, o))
        self._final = view(lib.graspd_env_final_observations(self._h), shape=(n, o))
        self._rewards = view(lib.graspd_env_rewards(self._h), shape=(n,))
        self._dones = view(lib.graspd_env_dones(self._h), shape=(n,))
        self._successes = view(lib.graspd_env_successes(self._h), shape=(n,))
        self._expert = np.zeros((n, self.action_len), dtype=np.float32)

    def reset(self, seed=None):
        """The observations; with ``seed``, every environment started afresh first
        (environment i with seed ``seed + i``). The environments come reset
        from the constructor (seeds ``seed + i`` of its own ``seed``)."""
        if seed is not None and _lib().graspd_env_reset(self._handle(), int(seed)) != 0:
            raise _error()
        return self._obs

    def step(self, actions):
        """One control step of every environment: (obs, rewards, terminated, truncated, info)."""
        a = np.ascontiguousarray(actions, dtype=np.float32)
        if a.shape != (self.num_envs, self.action_len):
            raise SimError(f"actions of shape {a.shape}: expected ({self.num_envs}, {self.action_len})")
        ptr = a.ctypes.data_as(ctypes.POINTER(ctypes.c_float))
        if _lib().graspd_env_step(self._handle(), ptr, a.size) != 0:
            raise _error()
        dones = self._dones.astype(bool)
        info = {"success": self._successes.astype(bool)}
        if dones.any():
            info["final_observation"] = self._final
            info["episodes"] = self.finished_episodes()
        return self._obs, self._rewards, np.zeros_like(dones), dones, info

    def expert_actions(self):
        """The scripted controllers' actions for the next step (demonstrations; privileged state)."""
        ptr = self._expert.ctypes.data_as(ctypes.POINTER(ctypes.c_float))
        if _lib().graspd_env_expert_actions(self._handle(), ptr, self._expert.size) != 0:
            raise _error()
        return self._expert

    def finished_episodes(self):
        """The episodes finished since the last call: env, instance, seed, success, return, steps, grasp."""
        text = _lib().graspd_env_drain_finished(self._handle())
        if text is None:
            raise _error()
        return json.loads(text)

    def close(self):
        """Frees the simulator; the arrays handed out before are invalid after this."""
        if self._h:
            _lib().graspd_env_free(self._h)
            self._h = None

    def _handle(self):
        if not self._h:
            raise SimError("the environments are closed")
        return self._h

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def __del__(self):
        try:
            self.close()
        except Exception:
            pass
