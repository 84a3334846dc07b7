"""Shared pytest fixtures."""
from pathlib import Path

import pytest

from pointfence.native import check_calls

# the tick's compiled calls (native.fast) convert no argument; under the tests each checks its
# arguments against its signature first, so a wrong type fails a test instead of the tick
check_calls()

#: Real depth recordings (SPEC section 8) live beside the project, never inside it.
SHARED_DATA = Path(__file__).parents[1].parent / "shared" / "data"


@pytest.fixture
def shared_data() -> Path:
    """Path to ../shared/data; skips the test when the folder is absent."""
    if not SHARED_DATA.is_dir():
        pytest.skip("../shared/data not found: real-data tests need the shared folder beside the project")
    return SHARED_DATA


@pytest.fixture(scope="session")
def ros2_env(tmp_path_factory) -> dict:
    """The machine-local ROS 2 environment of this test session (service/ros2/dds.py: a domain
    of its own, discovery on localhost, a loopback-only Fast DDS profile), applied to this
    process before any rclpy participant exists; pass it to child processes' ``env``. Skips
    when rclpy is not installed (``pip install 'pointfence[ros2]'``; `make test` installs it)."""
    from pointfence.service.ros2 import dds

    if not dds.available():
        pytest.skip("ROS 2 (rclpy) is not installed: pip install 'pointfence[ros2]'")
    env = dds.local_env(dds.unique_domain_id(), tmp_path_factory.mktemp("dds"))
    dds.apply(env)
    return env
