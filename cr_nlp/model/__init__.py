"""The robot model: robot files, PCC kinematics on three backends (JAX, CasADi, numpy),
tendons and their routing, limits, pose error, the actuation model from motor commands
(``actuation``, ``history``), loads (``loads``) and the Cosserat rod (``cosserat``: its
statics, the model that is right under load). Units: metres, radians, newtons."""

from .actuation import Actuation as Actuation
from .actuation import commands_for_configuration as commands_for_configuration
from .actuation import configuration_from_commands as configuration_from_commands
from .actuation import predict_tip as predict_tip
from .kinematics import CasadiModel as CasadiModel
from .kinematics import backbone_points as backbone_points
from .kinematics import backbone_points_z as backbone_points_z
from .kinematics import pose_error as pose_error
from .kinematics import pose_error_vector as pose_error_vector
from .kinematics import q_to_z as q_to_z
from .kinematics import q_to_z_numpy as q_to_z_numpy
from .kinematics import tendon_lengths as tendon_lengths
from .kinematics import tendon_lengths_z as tendon_lengths_z
from .kinematics import tip_pose as tip_pose
from .kinematics import tip_pose_z as tip_pose_z
from .kinematics import z_to_q as z_to_q
from .kinematics import z_to_q_numpy as z_to_q_numpy
from .robot import ModelFileError as ModelFileError
from .robot import Robot as Robot
from .robot import Segment as Segment
from .robot import Tendons as Tendons
from .robot import load_robot as load_robot
