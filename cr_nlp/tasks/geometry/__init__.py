"""The geometry family of tasks: IK (``ik``), trajectory planning (``trajectory``), path
following (``follow``) and live IK (``live_ik``) on the piecewise-constant-curvature model
(``model.kinematics``), with their results (``_ik_result``, ``_trajectory_result``,
``_follow_result``) and exact-mode hand-offs to ``stages.polish`` (``_ik_polish``,
``_trajectory_polish``, ``_follow_polish``). The mechanics family (``tasks.mechanics``) has
the same pattern on the Cosserat rod. Units: metres, radians, seconds."""
