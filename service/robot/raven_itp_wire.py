"""The Raven II's ITP wire form, from the master console's side (robot/raven_itp.py drives a
real Raven II with it).

Everything here follows the Raven II control software (github.com/uw-biorobotics/raven2):
``include/itp_teleoperation.h`` (the packets), ``src/raven/network_layer.cpp`` (how the Raven
reads them: sequence rules, ``UDPChecksum``), ``src/raven/local_io.cpp`` (``teleopIntoDS1``: how
the increments are integrated) and ``src/raven/mapping.cpp`` (``fromITP``: the ITP frame to the
arm's base frame). clients/PROTOCOL.md quotes the layouts with their offsets.

``u_struct`` (master -> Raven, 124 bytes, packed, little-endian on the x86 hosts): the
``service/itp.ITP`` struct (the same layout, read there by pointfence's own ITP receiver).
``v_struct`` (Raven -> master, 52 bytes): sent by the Raven only when built with ``NET_SEND``.
"""
from __future__ import annotations

import struct

import numpy as np

from ..itp import ITP, ITP_SIZE, udp_checksum

#: v_struct: uint32 sequence, last_sequence, pactyp, version; int32 fx[2], fy[2], fz[2], runlevel;
#: uint32 jointflags; int32 checksum
V_STRUCT = struct.Struct("<4I6iiIi")
V_SIZE = V_STRUCT.size       # 52
assert ITP_SIZE == 124 and V_SIZE == 52

#: u_struct arm slots (local_io.cpp teleopIntoDS1: GOLD_ARM_SERIAL -> 0, GREEN_ARM_SERIAL -> 1)
ARM_SLOT = {"left": 0, "right": 1}
#: surgeon_mode values (itp_teleoperation.h)
SURGEON_ENGAGED, SURGEON_DISENGAGED = 1, 0
#: runlevels in v_struct (include/raven/defines.h)
RUNLEVELS = {0: "E-STOP", 1: "INIT", 2: "PEDAL UP", 3: "PEDAL DOWN"}
#: runlevels in which the Raven follows (or is ready to follow) its master
RUNLEVELS_READY = (2, 3)
#: grasp limits of the Raven's integrated grasp command (local_io.cpp: graspmax = (int)(pi/2 * 1000),
#: graspmin = (int)(-10 deg * 1000), in milliradians)
GRASP_MAX_MRAD = 1570
GRASP_MIN_MRAD = -174
#: the packets a master must send before the Raven accepts its increments whatever sequence it last
#: saw: network_layer.cpp resets its count on the first packet when it last saw more than 1001
#: (``seq > 1000 && u.sequence < seq - 1000``: the packet is dropped), and otherwise drops packets
#: as out of sequence until ours pass the one it last saw (at most 1001)
SYNC_PACKETS = 1001

#: ITP frame -> arm base frame, mapping.cpp ``fromITP`` (the default build, without ORIENTATION_V):
#: ``incr = ITP2arm * incr * ITP2arm^-1`` for the position increment and the rotation increment
ITP_TO_BASE = {
    "left": np.array([[0.0, 0.0, -1.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]),    # ITP2Gold
    "right": np.array([[0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]),   # ITP2Green
}


def pack_u(buf: bytearray, sequence: int, slot: int, d_itp, q_itp, grasp: int, surgeon_mode: int) -> None:
    """Write a u_struct into ``buf`` (124 bytes): increments ``d_itp`` (3 ints, micrometres, ITP
    frame) and the rotation increment ``q_itp`` (x, y, z, w, ITP frame) for arm ``slot``; the other
    slot carries zero increments and the identity rotation (the Raven multiplies every active arm's
    orientation by its slot's quaternion: a zero quaternion would destroy the other arm's); grasp
    increment ``grasp`` (mrad; the Raven subtracts it from its grasp command); buttons 0;
    pactyp and version 0; the checksum by ``udp_checksum``."""
    dx, dy, dz = [0, 0], [0, 0], [0, 0]
    qx, qy, qz, qw = [0.0, 0.0], [0.0, 0.0], [0.0, 0.0], [1.0, 1.0]
    g = [0, 0]
    dx[slot], dy[slot], dz[slot] = d_itp
    qx[slot], qy[slot], qz[slot], qw[slot] = q_itp
    g[slot] = grasp
    buttons = (0, 0)
    c = udp_checksum(sequence, dx, dy, dz, buttons, surgeon_mode)
    ITP.pack_into(buf, 0, sequence, 0, 0, dx[0], dx[1], dy[0], dy[1], dz[0], dz[1], qx[0], qx[1], qy[0], qy[1],
                  qz[0], qz[1], qw[0], qw[1], buttons[0], buttons[1], g[0], g[1], surgeon_mode, c)


def unpack_v(data) -> tuple:
    """A v_struct's fields: (sequence, last_sequence, pactyp, version, fx, fy, fz, runlevel,
    jointflags, checksum); ``fx``... are (arm 0, arm 1) pairs. The caller checks the size."""
    v = V_STRUCT.unpack_from(data, 0)
    return v[0], v[1], v[2], v[3], v[4:6], v[6:8], v[8:10], v[10], v[11], v[12]


def pack_v(sequence: int, last_sequence: int, runlevel: int, forces=((0, 0), (0, 0), (0, 0)), jointflags: int = 0,
           pactyp: int = 0, version: int = 0, checksum: int = 0) -> bytes:
    """A v_struct (what a Raven built with NET_SEND sends; the simulated Raven of the tests)."""
    (fx, fy, fz) = forces
    return V_STRUCT.pack(sequence, last_sequence, pactyp, version, fx[0], fx[1], fy[0], fy[1], fz[0], fz[1],
                         runlevel, jointflags, checksum)


def newer(a: int, b: int) -> bool:
    """Sequence ``a`` after ``b`` (32-bit, wrapping)."""
    d = (a - b) & 0xFFFFFFFF
    return 0 < d < 0x80000000
