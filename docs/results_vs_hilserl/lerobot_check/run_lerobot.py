"""Run LeRobot 0.4.4's own HIL-SERL actor (lerobot.rl.actor.actor_cli) and learner (lerobot.rl.learner.train)
in ONE process (two threads, gRPC over localhost, concurrency=threads) on gym-hil PandaPickCube with state
observations and a scripted intervention. Only change to LeRobot: lerobot.rl.actor.make_robot_env is replaced,
because the stock one hard-codes image_obs=True and render_mode="human" for gym_hil (needs a display and a
keyboard/gamepad). Usage: python run_lerobot.py SEED ONLINE_STEPS OUTDIR"""
import os
import sys
import threading
import time
from pathlib import Path

import torch
import tv_stub  # noqa: F401  (see stubs/tv_stub.py)

torch.set_num_threads(1)

import lerobot.rl.actor as actor_mod  # noqa: E402
import lerobot.rl.learner as learner_mod  # noqa: E402
from lerobot.configs.train import TrainRLServerPipelineConfig  # noqa: E402
from lerobot.configs.types import FeatureType, PolicyFeature  # noqa: E402
from lerobot.envs.configs import GripperConfig, HILSerlProcessorConfig, HILSerlRobotEnvConfig, ResetConfig  # noqa
from lerobot.policies.sac.configuration_sac import ActorLearnerConfig, SACConfig  # noqa: E402
from scripted import make_env  # noqa: E402

seed = int(sys.argv[1])
steps = int(sys.argv[2])
out = Path(sys.argv[3]).resolve()
out.mkdir(parents=True, exist_ok=True)
csv_path = str(out / "episodes.csv")
port = 50051 + seed


def patched_make_robot_env(cfg):
    import numpy as np
    np.random.seed(seed)  # gym-hil samples the cube with the global np.random
    return make_env(random_block=True, csv_path=csv_path, seed=seed), None


actor_mod.make_robot_env = patched_make_robot_env

# LeRobot 0.4.4 bug: TrainPipelineConfig.validate() reads self.dataset.repo_id (configs/train.py:129) although
# TrainRLServerPipelineConfig.dataset defaults to None -> AttributeError. Give validate() a dummy, then restore None.
import types  # noqa: E402

_orig_validate = TrainRLServerPipelineConfig.validate


def _validate(self):
    ds = self.dataset
    if ds is None:
        self.dataset = types.SimpleNamespace(repo_id=None, root=None)
    try:
        _orig_validate(self)
    finally:
        self.dataset = ds


TrainRLServerPipelineConfig.validate = _validate


def make_cfg():
    state = PolicyFeature(type=FeatureType.STATE, shape=(18,))
    envst = PolicyFeature(type=FeatureType.ENV, shape=(3,))
    act = PolicyFeature(type=FeatureType.ACTION, shape=(3,))
    env = HILSerlRobotEnvConfig(
        name="gym_hil", task="PandaPickCubeBase-v0", fps=1000,  # ~no sleep; None crashes actor.py:727
        features={"agent_pos": state, "environment_state": envst, "action": act},
        features_map={"agent_pos": "observation.state", "environment_state": "observation.environment_state",
                      "action": "action"},
        processor=HILSerlProcessorConfig(control_mode="scripted",
                                         gripper=GripperConfig(use_gripper=True, gripper_penalty=-0.02),
                                         reset=ResetConfig(terminate_on_success=True)),
    )
    policy = SACConfig(
        device="cpu", storage_device="cpu", online_steps=steps, online_step_before_learning=100,
        num_discrete_actions=3, use_torch_compile=False, push_to_hub=False,
        input_features={"observation.state": state, "observation.environment_state": envst},
        output_features={"action": act},
        dataset_stats={
            "observation.state": {"min": [-3.0] * 18, "max": [3.0] * 18},
            "observation.environment_state": {"min": [0.2, -0.3, 0.0], "max": [0.6, 0.3, 0.5]},
            "action": {"min": [-1.0, -1.0, -1.0], "max": [1.0, 1.0, 1.0]},
        },
        actor_learner_config=ActorLearnerConfig(learner_port=port),
    )
    return TrainRLServerPipelineConfig(
        policy=policy, env=env, output_dir=out / "lerobot", job_name=f"gymhil_state_s{seed}", seed=seed,
        batch_size=256, save_checkpoint=False, log_freq=50,
    )


t0 = time.time()
lcfg = make_cfg()
th = threading.Thread(target=learner_mod.train, args=(lcfg,), daemon=True)
th.start()
time.sleep(10)
acfg = make_cfg()
acfg.output_dir = out / "lerobot_actor"
actor_mod.actor_cli(acfg)
print(f"DONE seed={seed} steps={steps} wall_s={time.time() - t0:.1f}", flush=True)
os._exit(0)
