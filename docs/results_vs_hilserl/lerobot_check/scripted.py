"""Scripted intervention for gym-hil PandaPickCube (state obs), replacing gym-hil's InputsControlWrapper
(keyboard/gamepad). It sets the same info keys InputsControlWrapper sets ("is_intervention", "teleop_action",
"rerecord_episode"), so LeRobot's GymHILAdapterProcessorStep / actor record the executed action and the flag.
Also logs one CSV row per episode (env reward sum, success, intervened steps)."""
import csv
import time

import gymnasium as gym
import numpy as np

STEP = 0.025  # gym-hil DEFAULT_EE_STEP_SIZE (m per unit action)


class ScriptedPicker:
    """Move above the cube, descend, close, lift. Action: [dx,dy,dz] in [-1,1], gripper in {0 open,1 stay,2 close}."""

    def __init__(self):
        self.reset()

    def reset(self):
        self.closed_for = 0

    def __call__(self, obs):
        tcp = np.asarray(obs["agent_pos"], np.float64)[-3:]
        cube = np.asarray(obs["environment_state"], np.float64)
        if self.closed_for > 0:
            self.closed_for += 1
            if self.closed_for < 4:
                return np.array([0, 0, 0, 2.0], np.float32)
            return np.array([0, 0, 1.0, 2.0], np.float32)  # lift
        err = cube - tcp
        xy = np.linalg.norm(err[:2])
        if xy > 0.01:
            target = np.array([cube[0], cube[1], max(tcp[2], cube[2] + 0.04)])
        else:
            target = cube.copy()
        d = target - tcp
        if xy <= 0.01 and abs(err[2]) < 0.01:
            self.closed_for = 1
            return np.array([0, 0, 0, 2.0], np.float32)
        a = np.clip(d / STEP, -1, 1)
        return np.array([a[0], a[1], a[2], 1.0], np.float32)


class ScriptedInterventionWrapper(gym.Wrapper):
    def __init__(self, env, episodes=(4, 5, 10, 19, 20, 28, 29), csv_path=None):
        super().__init__(env)
        self.episodes = set(episodes)
        self.episode = 0
        self.picker = ScriptedPicker()
        self.csv_path = csv_path
        self.t0 = time.time()
        self.total_steps = 0
        if csv_path:
            with open(csv_path, "w", newline="") as f:
                csv.writer(f).writerow(["episode", "total_steps", "ep_len", "return_env", "success",
                                        "intervened_steps", "wall_s"])

    def reset(self, **kw):
        obs, info = self.env.reset(**kw)
        self.episode += 1
        self.picker.reset()
        self.obs = obs
        self.ret, self.len, self.iv, self.succ = 0.0, 0, 0, False
        return obs, info

    def step(self, action):
        action = np.asarray(action, np.float32).reshape(-1)
        intervene = self.episode in self.episodes
        if intervene:
            action = self.picker(self.obs)
            self.iv += 1
        obs, rew, term, trunc, info = self.env.step(action)
        self.obs = obs
        self.ret += float(rew)
        self.len += 1
        self.total_steps += 1
        self.succ = self.succ or bool(info.get("succeed", False))
        info["is_intervention"] = intervene
        info["teleop_action"] = action
        info["rerecord_episode"] = False
        if (term or trunc) and self.csv_path:
            with open(self.csv_path, "a", newline="") as f:
                csv.writer(f).writerow([self.episode, self.total_steps, self.len, round(self.ret, 4),
                                        int(self.succ), self.iv, round(time.time() - self.t0, 1)])
        return obs, rew, term, trunc, info


def make_env(random_block=True, csv_path=None, episodes=(4, 5, 10, 19, 20, 28, 29), seed=0, max_steps=100):
    from gym_hil.wrappers.factory import make_env as hil_make_env

    env = hil_make_env("gym_hil/PandaPickCubeBase-v0", use_viewer=False, use_gripper=True,
                       use_inputs_control=False, gripper_penalty=-0.02, reset_delay_seconds=0.0,
                       image_obs=False, render_mode="rgb_array", random_block_position=random_block, seed=seed)
    env = gym.wrappers.TimeLimit(env, max_episode_steps=max_steps)
    return ScriptedInterventionWrapper(env, episodes=episodes, csv_path=csv_path)


if __name__ == "__main__":
    np.random.seed(0)
    env = make_env(episodes=range(1, 100), csv_path="/tmp/scripted_test.csv")
    for ep in range(5):
        obs, _ = env.reset()
        done = False
        while not done:
            obs, r, te, tr, info = env.step(np.zeros(4))
            done = te or tr
    print(open("/tmp/scripted_test.csv").read())
