"""The robot layer: a CRTK-style interface, a simulated Raven II arm and a Cartesian point mass.

>>> from pointfence.service.robot import make_robot
>>> robot = make_robot("raven2")                 # or "point-mass"; options: see factory.py
>>> x = robot.measured_cp()[:3, 3]                # tool tip, world frame (= robot base frame)
>>> robot.servo_cp(x + [0.0, 0.0, 0.00005])      # every tick: a small Cartesian increment
True
>>> robot.step(1e-3)                              # advance the simulation one 1 kHz tick

``hold()`` freezes the setpoint (stale camera, silent client, NaN, failed kernel); ``resume()``
continues without moving. A bad command raises pointfence.kernels.errors.InputError and changes
nothing. See base.py for the contract, raven2.py / raven2_kinematics.py for the arm and its
kinematic conventions, point_mass.py for the minimal robot, factory.py for the ``[robot]`` table.
"""
from .base import Command, JointState, Robot, RobotMode, RobotState
from .factory import MODELS, make_robot, model_options, robot_from_config
from .point_mass import PointMass
from .raven2 import Raven2
from .raven2_kinematics import JOINT_HOME, JOINT_LOWER, JOINT_NAMES, JOINT_UPPER, Raven2Kinematics

__all__ = ["Command", "JointState", "Robot", "RobotMode", "RobotState", "MODELS", "make_robot", "model_options",
           "robot_from_config", "PointMass", "Raven2", "Raven2Kinematics", "JOINT_HOME", "JOINT_LOWER",
           "JOINT_NAMES", "JOINT_UPPER"]
