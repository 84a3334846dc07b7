"""`pointfence ros2 SUBCOMMAND`: pointfence's ROS 2 nodes, each a module named in ``SUBCOMMANDS``
that provides ``add_arguments(parser)`` and ``run(args) -> int`` (imported only when used).

``--localhost`` keeps DDS on this machine (dds.local_env: a domain of its own unless
``--domain-id`` is given, discovery on 127.0.0.1 only), as the tests and benches run them."""
from __future__ import annotations

import importlib
import sys

from . import dds

#: subcommand -> (module, one-line help)
SUBCOMMANDS: dict = {
    "camera-node": ("pointfence.service.ros2.camera_node", "publish a pointfence depth source as a ROS 2 camera (Image/compressedDepth + CameraInfo)"),
    "sim-master": ("pointfence.service.ros2.sim_master", "a simulated CRTK master (dVRK MTM): measured_cp and the pedal out, body/servo_cf forces in"),
    "sim-arm": ("pointfence.service.ros2.sim_arm", "a simulated arm (raven2, point-mass) as a CRTK ROS 2 node"),
}


def add_arguments(p):
    p.add_argument("--localhost", action="store_true",
                   help="keep DDS on this machine (loopback-only Fast DDS profile, discovery range LOCALHOST)")
    p.add_argument("--domain-id", type=int, default=None, help="ROS_DOMAIN_ID for this process (0-232)")
    sub = p.add_subparsers(dest="ros2_command", metavar="SUBCOMMAND")
    argv = sys.argv[1:]
    for name, (module, help_) in SUBCOMMANDS.items():
        sp = sub.add_parser(name, help=help_, description=help_)
        sp.set_defaults(_ros2_module=module)
        if name in argv:   # filled in only for the chosen subcommand (fast start)
            importlib.import_module(module).add_arguments(sp)


def run(args) -> int:
    if not getattr(args, "ros2_command", None):
        print("pointfence ros2: name a subcommand: " + ", ".join(SUBCOMMANDS), file=sys.stderr)
        return 2
    if args.localhost:
        domain = dds.unique_domain_id() if args.domain_id is None else args.domain_id
        dds.apply(dds.local_env(domain))
    elif args.domain_id is not None:
        dds.apply({"ROS_DOMAIN_ID": str(dds.check_domain_id(args.domain_id))})
    return int(importlib.import_module(args._ros2_module).run(args) or 0)
