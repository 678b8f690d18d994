"""A robot bridge that another client holds, over real Zenoh on loopback: for the tests of the
bridge's clients (the actor, the evaluator) while the gripper is not theirs."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import zenoh

from nasa.up import free_port
from services.robot_bridge.client import BridgeEnv
from services.robot_bridge.server import BridgeServer
from shared.gripper.sim import ValveSim
from shared.zenoh_session import open_client, open_router

HOLD_S = 600.0
"""Longer than any test: the holder keeps the gripper until a test lowers `server.hold.hold_s`."""


@contextlib.contextmanager
def held_bridge(bridge_id: str, holder: str) -> Iterator[tuple[BridgeServer, zenoh.Session, zenoh.Session]]:
    """The gripper stand-in (32x32 frames, as `tests.tiny.tiny_gripper_run`) behind bridge
    `bridge_id`, which a client named `holder` has reset: yields the bridge, a session for the client
    under test, and the holder's session."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    sim = ValveSim("gripper-valve", seed=7, image_size=32, render_quality="fast")
    try:
        with (open_router(endpoint), open_client(endpoint) as bridge_session,
              open_client(endpoint) as session, open_client(endpoint) as holder_session):
            server = BridgeServer(bridge_session, bridge_id, sim, "gripper-valve", log=lambda _: None,
                                  hold_s=HOLD_S)
            with server.serve():
                BridgeEnv(holder_session, bridge_id, client=holder).reset()
                yield server, session, holder_session
    finally:
        sim.close()
