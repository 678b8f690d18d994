"""The gripper environment source: spec, stand-in, and a bridge behind the same spec."""

import numpy as np
import pytest

from shared import envs
from shared.config import EnvConfig
from shared.gripper.source import BridgeMismatch, GripperSource

pytestmark = pytest.mark.skipif(
    not hasattr(envs, "EnvSpec"), reason="needs the environment seam (EnvSpec, EnvSource) of shared/envs.py"
)


def test_spec_matches_the_built_stand_in_and_its_state_round_trips() -> None:
    source = GripperSource()
    assert source.tasks() == ["gripper-valve", "gripper-valve_reset"]
    config = EnvConfig(task="gripper-valve_reset", image_size=64, frame_stack=3, render_quality="fast")
    spec = source.spec(config)
    env = source.make(config, seed=3)
    ts = env.reset()
    assert env.spec == spec and ts.frame.shape == spec.frame_shape and ts.obs.shape == spec.obs_shape
    assert env.action_dim == spec.action_dim == 4
    state = env.rng_state()
    for _ in range(3):
        ts = env.step(np.zeros(4))
        assert ts.obs.shape == spec.obs_shape and -1.0 <= ts.reward <= 0.0
    again = source.make(config, seed=99)
    again.set_rng_state(state)
    assert again.rng_state()["keys"] == state["keys"]


def test_a_bridge_behind_the_same_spec(tmp_path) -> None:
    from nasa.up import free_port
    from services.robot_bridge.server import BridgeServer
    from shared.gripper.sim import ValveSim
    from shared.zenoh_session import open_client, open_router

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    sim = ValveSim("gripper-valve", seed=0, render_quality="fast")
    with open_router(endpoint), open_client(endpoint) as bridge, open_client(endpoint) as actor:
        try:
            with BridgeServer(bridge, "src", sim, "gripper-valve", log=lambda _: None).serve():
                config = EnvConfig(task="gripper-valve")
                env = GripperSource().make_remote(config, actor, "src", "test")
                assert env.spec == GripperSource().spec(config)
                assert env.reset().obs.shape == env.spec.obs_shape
                with pytest.raises(BridgeMismatch, match="gripper-valve_reset"):
                    GripperSource().make_remote(EnvConfig(task="gripper-valve_reset"), actor, "src", "test")
                with pytest.raises(BridgeMismatch, match="--action-repeat 1"):
                    repeated = EnvConfig(task="gripper-valve", action_repeat=8)
                    GripperSource().make_remote(repeated, actor, "src", "test")
        finally:
            sim.close()
