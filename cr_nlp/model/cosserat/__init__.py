"""Cosserat-rod statics of a tendon-driven robot, batched in JAX.

The model is Rucker & Webster's (IEEE T-RO 2011; the rod and its integration:
``_rod``): an elastic backbone with strains v (shear, extension) and u (bending,
torsion), each tendon a frictionless string routed parallel to the backbone at ``r_i`` in
the disks' frame, pulling with tension τ_i ≥ 0 and ending at the end of its segment
(per-segment routing) or at the tip (shared routing).

How it is solved. Cut the robot at arc length s and take everything distal of the cut,
tendons included: the force N and moment M that cross the cut obey the plain rod
equations with the external loads only, so N(s) is known in closed form and the only
unknown is M(0) (3 numbers), found by shooting on ``M(L) = M_tip`` (``_shooting``).
Without an external force N ≡ 0, so M(0) = M_tip plus the point moments, with no
iteration.

Which equilibrium. Past a buckling load one set of loads has several equilibria. The
shooting continues in a load factor λ that scales the external loads, and in the loading
path the tensions too, from 0 (M(0) = 0 exactly) to 1, following the branch; where the
branch ends in a fold before λ = 1 (a snap-through) it stops and records λ. The batched
driver, ``solve_statics`` (``_statics``), decides which start a case needs, tests each
answer's stability (``_equilibria``) and counts the equilibria it finds.

The solution M(0) is differentiated implicitly (``jax.lax.custom_root``): derivatives of
the shape with respect to tensions and loads cost one 3×3 solve, not the unrolled
iterations. Units: metres, radians, newtons, N·m, kg, m/s².

The public face: ``solve_statics`` (batched, numpy in, float64 numpy out), its settings
``StaticsConfig`` and its result ``StaticsResult`` (with ``Equilibrium``). For the solver
stages on the rod: the one-case programs (``tip_equilibrium``, ``backbone_equilibrium``,
``statics_single``, ``case_loads``, ``CaseLoads``, ``moment_scale``), one case settled from
a nearby equilibrium inside a caller's program (``settle_function``, its arguments
``settle_arguments`` and its ``settled_statics``: the live update's verdict run after its
LM in one program) and the same RK4 steps for CasADi (``CasadiRod``, ``RodLoads``,
``flat_loads``; ``_casadi``). Driven by motor commands instead of tensions:
``solve_displacement_statics`` and its ``DisplacementStaticsResult`` (``_displacement``: the
tensions that make each tendon's path match its command, slack tendons carrying none; the
segments' take-up ``take_up_lengths``), its inverse ``motor_commands`` and, for the calibration,
``predict_marker``, ``displacement_pass`` and ``displacement_solver``.
"""

from ._casadi import CasadiRod as CasadiRod
from ._casadi import RodLoads as RodLoads
from ._casadi import flat_loads as flat_loads
from ._displacement import DisplacementStaticsResult as DisplacementStaticsResult
from ._displacement import displacement_pass as displacement_pass
from ._displacement import displacement_solver as displacement_solver
from ._displacement import motor_commands as motor_commands
from ._displacement import predict_marker as predict_marker
from ._displacement import solve_displacement_statics as solve_displacement_statics
from ._displacement import take_up_lengths as take_up_lengths
from ._rod import CaseLoads as CaseLoads
from ._rod import StaticsConfig as StaticsConfig
from ._shooting import Equilibrium as Equilibrium
from ._shooting import StaticsResult as StaticsResult
from ._shooting import backbone_equilibrium as backbone_equilibrium
from ._shooting import case_loads as case_loads
from ._shooting import moment_scale as moment_scale
from ._shooting import statics_single as statics_single
from ._shooting import tip_equilibrium as tip_equilibrium
from ._statics import settle_arguments as settle_arguments
from ._statics import settle_function as settle_function
from ._statics import settled_statics as settled_statics
from ._statics import solve_statics as solve_statics
