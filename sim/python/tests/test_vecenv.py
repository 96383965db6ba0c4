"""graspd_sim.VecEnv: the tasks stepped by actions from Python (run by sim/ffi/tests/python.rs)."""

import numpy as np
import pytest

from graspd_sim import SimError, VecEnv


@pytest.fixture(scope="module")
def place():
    env = VecEnv("place", instances=["mug_canonical", "mug_train_03"], num_envs=4, threads=2, seed=100)
    yield env
    env.close()


def run_expert(env, steps):
    """The expert's steps, each result copied (the arrays are views refreshed in place)."""
    out = []
    views = env.reset()
    for _ in range(steps):
        o, r, term, trunc, info = env.step(env.expert_actions())
        assert o is views  # the same zero-copy view, refreshed in place
        out.append((o.copy(), r.copy(), term.copy(), trunc.copy(), info))
    return out


def test_the_expert_places_every_mug_through_actions(place):
    obs = place.reset(100)
    assert obs.shape == (4, place.observation_len) and obs.dtype == np.float32
    assert place.info["instances"] == ["mug_canonical", "mug_train_03"] * 2
    assert place.info["steps_per_episode"] == 300
    returns = np.zeros(4)
    for k, (o, r, term, trunc, info) in enumerate(run_expert(place, 300)):
        assert np.isfinite(r).all() and not term.any()
        returns += r
        assert trunc.all() == (k == 299) and (trunc.any() == (k == 299))
    episodes = info["episodes"]
    assert [(e["env"], e["seed"]) for e in episodes] == [(0, 100), (1, 101), (2, 102), (3, 103)]
    assert all(e["success"] and e["steps"] == 300 for e in episodes), episodes
    assert np.allclose([e["episode_return"] for e in episodes], returns, rtol=1e-4)
    # Reset at once with the next seeds: a new goal in the same row.
    goal = place.observation_layout["goal_position"]
    assert not np.array_equal(info["final_observation"][:, goal], place.reset()[:, goal])


def test_same_seed_same_episode(place):
    def trace():
        place.reset(7)
        return np.stack([o[:, :7] for o, *_ in run_expert(place, 40)])

    assert np.array_equal(trace(), trace())


def test_bad_actions_are_refused_and_nothing_steps(place):
    place.reset(3)
    before = place.reset().copy()
    with pytest.raises(SimError, match="expected"):
        place.step(np.zeros((4, 3)))
    bad = np.zeros((4, place.action_len), dtype=np.float32)
    bad[1, 6] = np.inf
    with pytest.raises(SimError, match="environment 1"):
        place.step(bad)
    assert np.array_equal(place.reset(), before)


def test_each_task_runs_and_bad_configurations_are_refused():
    for task, tool in [("position", "drill_canonical"), ("nail", "hammer_canonical")]:
        with VecEnv(task, instances=tool, num_envs=2, seed=0) as env:
            assert env.info["task"] == task
            o, r, *_ = env.step(env.expert_actions())
            assert o.shape == (2, env.observation_len) and np.isfinite(r).all()
    for kwargs, words in [
        ({"task": "cook"}, "task `cook`"),
        ({"task": "place", "instances": "drill_canonical"}, "no mug instance"),
        ({"task": "place", "num_envs": 0}, "at least one environment"),
        ({"task": "place", "grasp_from": "carrier pigeon"}, "grasp source"),
    ]:
        with pytest.raises(SimError, match=words):
            VecEnv(**kwargs)
