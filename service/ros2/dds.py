"""The DDS environment of a ROS 2 process, and rclpy's import with a useful error.

A lab's setup spans machines, so the product leaves ROS 2's own environment alone
(``ROS_DOMAIN_ID``, ``ROS_AUTOMATIC_DISCOVERY_RANGE``, a Fast DDS profile) unless told to keep
DDS on this machine: tests, benches and CI must never send discovery traffic to another address.
``local_env`` gives that environment (a domain of its own, discovery limited to localhost, and a
Fast DDS profile whose only transports are shared memory (depth images of 600 kB cross it without
UDP fragmentation) and UDP on 127.0.0.1, with 127.0.0.1 as the only initial peer and no built-in
transports: nothing on another interface);
``apply`` puts it into ``os.environ`` before rclpy creates its first participant, and a child
process gets it through its ``env``.
"""
from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Mapping, Optional

from pointfence.kernels.errors import BackendUnavailable, InputError

#: Fast DDS' port formula (7400 + 250 x domain + offsets) fits a 16-bit port up to domain 232
MAX_DOMAIN_ID = 232

PROFILE_XML = """<?xml version="1.0" encoding="UTF-8" ?>
<!-- pointfence: DDS on this machine only (shared memory, and UDP over 127.0.0.1; no other transport) -->
<profiles xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles">
  <transport_descriptors>
    <transport_descriptor>
      <transport_id>pointfence_loopback</transport_id>
      <type>UDPv4</type>
      <interfaceWhiteList><address>127.0.0.1</address></interfaceWhiteList>
    </transport_descriptor>
    <transport_descriptor>
      <transport_id>pointfence_shm</transport_id>
      <type>SHM</type>
      <segment_size>16777216</segment_size>
    </transport_descriptor>
  </transport_descriptors>
  <participant profile_name="pointfence_loopback_only" is_default_profile="true">
    <rtps>
      <userTransports>
        <transport_id>pointfence_shm</transport_id>
        <transport_id>pointfence_loopback</transport_id>
      </userTransports>
      <useBuiltinTransports>false</useBuiltinTransports>
      <builtin>
        <initialPeersList>
          <locator><udpv4><address>127.0.0.1</address></udpv4></locator>
        </initialPeersList>
      </builtin>
    </rtps>
  </participant>
</profiles>
"""

INSTALL_HINT = ("install the ROS 2 extra (no ROS installation needed, CPython 3.10-3.13 on x86-64 Linux): "
                "pip install 'pointfence[ros2]'")


def write_profile(directory: Optional[Path] = None) -> Path:
    """Write the loopback-only Fast DDS profile into ``directory`` (default: a new temporary
    folder) and return its path."""
    d = Path(directory) if directory is not None else Path(tempfile.mkdtemp(prefix="pointfence-dds-"))
    d.mkdir(parents=True, exist_ok=True)
    path = d / "fastdds_loopback.xml"
    path.write_text(PROFILE_XML)
    return path


def check_domain_id(domain_id) -> int:
    """``domain_id`` as an int, or an ``InputError`` naming the valid range."""
    try:
        d = int(domain_id)
    except (TypeError, ValueError):
        d = -1
    if not 0 <= d <= MAX_DOMAIN_ID or str(domain_id).strip() != str(d):
        raise InputError(f"ROS_DOMAIN_ID = {domain_id!r}; expected an integer 0-{MAX_DOMAIN_ID} "
                         "(Fast DDS ports overflow above)")
    return d


def local_env(domain_id: int, directory: Optional[Path] = None) -> dict:
    """The environment variables that keep ROS 2 on this machine, in domain ``domain_id``
    (0-232): discovery range LOCALHOST, the loopback-only Fast DDS profile (written into
    ``directory``), Fast DDS as the middleware, and ROS logs in that folder, not ``~/.ros``."""
    domain_id = check_domain_id(domain_id)
    profile = write_profile(directory)
    return {"ROS_DOMAIN_ID": str(domain_id),
            "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
            "ROS_STATIC_PEERS": "",
            "FASTRTPS_DEFAULT_PROFILES_FILE": str(profile),
            "FASTDDS_DEFAULT_PROFILES_FILE": str(profile),
            "RMW_IMPLEMENTATION": "rmw_fastrtps_cpp",
            "ROS_LOG_DIR": str(profile.parent / "log")}


def unique_domain_id(seed: Optional[int] = None) -> int:
    """A domain id for one test or bench run (1-232), from ``seed`` (default: this process id),
    so that runs side by side on one machine do not see each other."""
    s = os.getpid() if seed is None else int(seed)
    return 1 + s % MAX_DOMAIN_ID


def apply(env: Mapping[str, str]) -> None:
    """Put ``env`` into this process' environment (before rclpy's first participant)."""
    os.environ.update({k: str(v) for k, v in env.items()})


def rclpy():
    """The ``rclpy`` module, or a ``BackendUnavailable`` that says how to install it."""
    try:
        import rclpy as mod
    except ImportError as e:
        raise BackendUnavailable(f"ROS 2 is not available here ({e}); {INSTALL_HINT}") from None
    return mod


def available() -> bool:
    """Whether rclpy and the standard message packages import here."""
    try:
        rclpy()
        import geometry_msgs.msg
        import sensor_msgs.msg
        del geometry_msgs, sensor_msgs
    except (BackendUnavailable, ImportError):
        return False
    return True
