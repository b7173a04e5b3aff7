"""The tasks, one package per model family, each task a config, a solver and a result:
``geometry`` (IK, trajectory planning, path following and live IK on the PCC model),
``mechanics`` (the same tasks in tension space on the Cosserat rod, under loads) and
``calibration`` (fitting a robot's actuation model to a recording). Shared by them: the
result protocol (``_result``), stage timing (``_timing``), reference paths (``paths``) and
every input file's reader (``readers``)."""
