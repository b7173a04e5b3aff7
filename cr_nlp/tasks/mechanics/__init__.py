"""The mechanics family of tasks: tension-space IK (``ik``), planning (``trajectory``) and
path following (``follow``) on the Cosserat rod model (``model.cosserat``), under gravity,
payloads and point loads; the independent verdict of a tension motion (``_motion``) and the
result types (``_ik_result``, ``_motion_result``). The geometry (PCC) family is the rest of
``tasks/``; both go through the stages of ``stages/``. Units: metres, radians, seconds,
newtons."""
