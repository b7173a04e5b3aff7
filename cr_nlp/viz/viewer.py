"""The interactive 3-D viewer in the browser (viser): a scene, a robot, and a result of
``cr-nlp ik``, ``plan`` or ``follow`` to orbit and replay, and live IK by dragging a target.

Everything a replay shows is computed once when the viewer starts (the robot's tube and
tendons at every waypoint, the closest obstacle point, tendon speeds); scrubbing only
sends precomputed geometry. Live IK re-solves with ``tasks.geometry.live_ik.LiveIKSolver``,
warm-started from the answer on screen; with ``model="cosserat"`` the target is solved
for tendon tensions on the Cosserat rod under the given loads (``_tension_live``) and the
rod's equilibrium is drawn. Lengths in metres, angles in radians, times in seconds.
"""

from __future__ import annotations

import contextlib
import io
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

try:
    import viser
except ImportError as exc:  # the optional extra
    raise ImportError("the viewer needs viser: pip install 'cr_nlp[viewer]'") from exc

from ..model import Robot, load_robot
from ..tasks._result import read_json
from ..world import Scene, load_scene
from ._replay import (
    Answers,
    Motion,
    RobotMesh,
    closest_obstacle_points,
    precompute,
    read_result,
    targets_of,
    tip_pose,
)
from ._tension_live import TensionLive
from ._viewer_scene import (
    CLOSEST_RGB,
    PALETTE,
    REFERENCE_RGB,
    ROBOT_RGB,
    TENDON_RGB,
    TRACE_RGB,
    add_scene,
    camera_aim,
    free_port,
    live_text,
)

__all__ = [
    "Answers",
    "Motion",
    "Viewer",
    "closest_obstacle_points",
    "free_port",
    "read_result",
    "targets_of",
    "tip_pose",
]

# ================================================================ the viewer


class Viewer:
    """A viser server showing a robot, a scene and a result; ``url`` is its address.

    Args:
        robot: a ``Robot``, a robot file or a bundled name ("tdcr3").
        scene: a ``Scene``, a scene file or bundled name, or None.
        result: a RESULT.json path of ``cr-nlp ik``, ``plan`` or ``follow``, its loaded
            content, or None (the robot straight, with live IK).
        port: TCP port; None picks a free one.
        host: the address to listen on (default localhost only).
        targets: for an ik result, the target poses (positions (T, 3) m, wxyz (T, 4)),
            drawn beside the reached ones.
        path: for a follow result, its reference path (file, bundled name or
            ``ReferencePath``) when the result's path name does not resolve.
        live_ik: offer live IK (a target gizmo; re-solves on every move).
        q: the configuration to show without a result (default straight).
        model, loads: "pcc", or "cosserat": live IK of tendon tensions on the rod under
            ``loads`` (``TensionLive.of``).
    """

    def __init__(
        self,
        robot: Robot | str | Path,
        scene: Scene | str | Path | None = None,
        result: Any = None,
        port: int | None = None,
        *,
        host: str = "127.0.0.1",
        targets: Any = None,
        path: Any = None,
        live_ik: bool = True,
        q: Any = None,
        model: str = "pcc",
        loads: dict[str, Any] | None = None,
    ) -> None:
        self.robot = load_robot(robot if not isinstance(robot, Path) else str(robot))
        self.scene = (
            load_scene(scene if not isinstance(scene, Path) else str(scene))
            if scene is not None and not isinstance(scene, Scene)
            else scene
        )
        source = ""
        if isinstance(result, str | Path):
            source, result = str(result), read_json(result)
        content = None if result is None else read_result(self.robot, result, targets, path,
                                                          source=source)
        self.motions: list[Motion] = content if isinstance(content, list) else []
        self.answers: Answers | None = content if isinstance(content, Answers) else None
        self._mesh = RobotMesh(self.robot)
        self._tension = TensionLive.of(model, loads, result, self.robot, self.scene, self._mesh)
        for motion in self.motions:
            precompute(motion, self._mesh, self.scene)
        straight = np.ravel([[0.0, 0.0, s.length_min] for s in self.robot.segments])
        self.q = (
            self.robot.full_q(np.ravel(q))
            if q is not None
            else self.motions[0].q[0]
            if self.motions
            else self.answers.q[0]
            if self.answers is not None
            else straight
        )
        """The configuration on screen (3n; rad, rad, m)."""
        self.last_live: Any = None
        """The last live-IK answer (``tasks.geometry.live_ik.LiveIKResult``), None before."""

        with contextlib.redirect_stdout(io.StringIO()):  # viser's banner: we print the url
            self.server = viser.ViserServer(
                host=host, port=free_port(host) if port is None else int(port), verbose=False
            )
        self.port = self.server.get_port()
        """The TCP port served (viser takes the next free one if ``port`` is taken)."""
        self.url = f"http://{host}:{self.port}"
        """The page's address."""
        self._motion = self.motions[0] if self.motions else None
        self._frame = 0
        self._stop = threading.Event()
        self._solve_lock = threading.Lock()
        self._solver_lock = threading.Lock()
        self._pending: tuple[np.ndarray, np.ndarray, bool] | None = None
        self._live_solver: Any = None
        self._live_on = live_ik and not self.motions and self.answers is None

        try:
            self._build_page(live_ik)
        except BaseException:
            self.server.stop()
            raise
        self._player = threading.Thread(target=self._play_loop, daemon=True)
        self._player.start()
        self._wake = threading.Event()
        self._solving = threading.Thread(target=self._live_loop, daemon=True)
        if live_ik:
            self._solving.start()
        # Not a daemon: a compile cut off at interpreter exit aborts the process.
        self._warming = threading.Thread(target=self._warm_up) if live_ik else None
        if self._warming is not None:
            self._warming.start()

    def _build_page(self, live_ik: bool) -> None:
        """The scene, the robot, the controls and the camera."""
        self.server.scene.set_up_direction("+z")
        add_scene(self.server, self.robot, self.scene)
        self._add_robot()
        self._add_gui(live_ik)
        self._aim_camera()
        if self._motion is not None:
            self.show_frame(0)
        elif self.answers is not None:
            self.show_answer(0)

    # ------------------------------------------------------------ robot
    def _add_robot(self) -> None:
        vertices, lines, _ = self._mesh.geometry(self.q)
        scene_api = self.server.scene
        self._body = scene_api.add_mesh_simple(
            "/robot/body", vertices, self._mesh.faces, color=ROBOT_RGB, opacity=0.55, side="double"
        )
        self._tendons = scene_api.add_line_segments(
            "/robot/tendons", lines, TENDON_RGB, thickness=0.006
        )
        motion = self._motion
        self._trace = self._reference = self._closest = self._closest_dot = None
        if motion is not None:
            self._add_motion_lines(motion)
        self._target_frame = self._reached_frame = None
        if self.answers is not None:
            self._target_frame = scene_api.add_frame(
                "/ik/target", axes_length=0.2, axes_radius=0.012, visible=False
            )
            self._reached_frame = scene_api.add_frame(
                "/ik/reached", axes_length=0.12, axes_radius=0.02, visible=False
            )

    def _add_motion_lines(self, motion: Motion) -> None:
        scene_api = self.server.scene
        tips = motion.tips if motion.tips is not None else np.zeros((1, 3))
        if len(tips) > 1:
            self._trace = scene_api.add_line_segments(
                "/motion/tip_trace", np.stack([tips[:-1], tips[1:]], 1), TRACE_RGB, thickness=0.012
            )
        if motion.reference is not None and len(motion.reference) > 1:
            ref = motion.reference
            self._reference = scene_api.add_line_segments(
                "/motion/reference",
                np.stack([ref[:-1], ref[1:]], 1),
                REFERENCE_RGB,
                thickness=0.008,
            )
        if motion.closest is not None:
            self._closest = scene_api.add_line_segments(
                "/motion/closest",
                motion.closest[:1].astype(np.float32),
                CLOSEST_RGB,
                thickness=0.015,
            )
            self._closest_dot = scene_api.add_icosphere(
                "/motion/closest_point",
                radius=0.03,
                color=CLOSEST_RGB,
                position=tuple(motion.closest[0, 1]),
            )

    def _aim_camera(self) -> None:
        camera = self.server.initial_camera
        camera.look_at, camera.position = camera_aim(self.robot, self.scene)

    # ------------------------------------------------------------ GUI
    def _add_gui(self, live_ik: bool) -> None:
        gui = self.server.gui
        scene_name = self.scene.name if self.scene is not None else "no scene"
        gui.add_markdown(f"**cr_nlp** · robot `{self.robot.name}` · scene `{scene_name}`")
        self._summary = gui.add_markdown("")
        self._status = gui.add_markdown("")
        if self.motions:
            if len(self.motions) > 1:
                choice = gui.add_dropdown(
                    "motion", [m.label for m in self.motions], initial_value=self.motions[0].label
                )

                @choice.on_update
                def _(_: Any) -> None:
                    self.select_motion([m.label for m in self.motions].index(choice.value))

            count = len(self.motions[0].q)
            self._time = gui.add_slider(
                "waypoint", min=0, max=max(count - 1, 1), step=1, initial_value=0
            )

            @self._time.on_update
            def _(_: Any) -> None:
                if int(self._time.value) != self._frame:
                    self.show_frame(int(self._time.value))

            controls = gui.add_button_group("replay", ["play", "pause"])

            @controls.on_click
            def _(_: Any) -> None:
                self.playing = controls.value == "play"

            self._speed = gui.add_slider("speed ×", min=0.25, max=4.0, step=0.25, initial_value=1.0)
            self.playing = False
            self._length_plot = self._speed_plot = None
            self._add_plots(self.motions[0])
        if self.answers is not None:
            count = len(self.answers.q)
            self._answer = gui.add_slider(
                "answer", min=0, max=max(count - 1, 1), step=1, initial_value=0, disabled=count < 2
            )

            @self._answer.on_update
            def _(_: Any) -> None:
                self.show_answer(int(self._answer.value))

        self._live_gizmo = None
        if live_ik:
            with gui.add_folder("live IK"):
                self._live_box = gui.add_checkbox(
                    "drag the target",
                    self._live_on,
                    hint="a gizmo at the tip; moving it re-solves from the answer shown",
                )
                if self._tension is None:  # no live Ipopt stage on the rod
                    self._exact_box = gui.add_checkbox("exact (Ipopt polish)", False)
                self._live_text = gui.add_markdown("")

            @self._live_box.on_update
            def _(_: Any) -> None:
                self.set_live(bool(self._live_box.value))

            self.set_live(self._live_on)

    def _add_plots(self, motion: Motion) -> None:
        gui = self.server.gui
        series: tuple[Any, ...] = ({"label": "t (s)"},) + tuple(
            {"label": name, "stroke": PALETTE[j % len(PALETTE)], "width": 1.5}
            for j, name in enumerate(motion.tendon_names)
        )
        scales = {"x": {"time": False}}
        data = (motion.times, *motion.tendon_lengths.T)
        self._length_plot = gui.add_uplot(
            data, series, title="tendon lengths (m)", scales=scales, aspect=1.6
        )
        speeds = (motion.times, *motion.tendon_speeds.T)
        self._speed_plot = gui.add_uplot(
            speeds, series, title="tendon speeds (m/s)", scales=scales, aspect=1.6
        )

    # ------------------------------------------------------------ replay
    def select_motion(self, index: int) -> None:
        """Show motion ``index`` (a plan result's problem) from its first waypoint."""
        motion = self.motions[index]
        self._motion = motion
        for handle in (self._trace, self._reference, self._closest, self._closest_dot):
            if handle is not None:
                handle.remove()
        self._trace = self._reference = self._closest = self._closest_dot = None
        self._add_motion_lines(motion)
        self._time.max = max(len(motion.q) - 1, 1)
        if self._length_plot is not None:
            self._length_plot.data = (motion.times, *motion.tendon_lengths.T)
            self._speed_plot.data = (motion.times, *motion.tendon_speeds.T)
        self.show_frame(0)

    def show_frame(self, k: int) -> None:
        """Show waypoint k of the current motion (precomputed: nothing is solved)."""
        motion = self._motion
        if motion is None:
            raise ValueError("no motion to show: the viewer has no plan or follow result")
        k = int(np.clip(k, 0, len(motion.q) - 1))
        self._frame = k
        self.q = motion.q[k]
        with self.server.atomic():
            self._body.vertices = motion.vertices[k]
            self._tendons.points = motion.tendon_lines[k]
            if motion.closest is not None and self._closest is not None:
                if np.all(np.isfinite(motion.closest[k])):
                    self._closest.points = motion.closest[k : k + 1].astype(np.float32)
                    self._closest_dot.position = tuple(motion.closest[k, 1])
            if int(self._time.value) != k:
                self._time.value = k
        self._summary.content = motion.summary
        speeds = motion.tendon_speeds[k]
        lines = [f"t = {motion.times[k]:.2f} s (waypoint {k} of {len(motion.q) - 1})"]
        if motion.clearance is not None:
            lines.append(
                f"clearance {motion.clearance[k]:.4f} m to "
                f"`{motion.closest_name[k] or '-'}` (python-fcl)"
            )
        lines.append(f"fastest tendon {np.max(np.abs(speeds)):.3f} m/s")
        self._status.content = "  \n".join(lines)
        if self._live_gizmo is not None:
            self._place_gizmo()

    @property
    def playing(self) -> bool:
        """Whether the replay advances by itself."""
        return self._playing

    @playing.setter
    def playing(self, value: bool) -> None:
        self._playing = bool(value)

    def _play_loop(self) -> None:
        while not self._stop.is_set():
            motion = self._motion
            if motion is None or not getattr(self, "_playing", False) or self._live_on:
                self._stop.wait(0.1)
                continue
            dt = float(np.median(np.diff(motion.times))) if len(motion.times) > 1 else 0.1
            if self._stop.wait(max(dt / float(self._speed.value), 0.02)):
                break
            if self._playing and not self._live_on:
                self.show_frame((self._frame + 1) % len(motion.q))

    # ------------------------------------------------------------ ik answers
    def show_answer(self, i: int) -> None:
        """Show IK answer i with its target and reached frames and its verdict."""
        answers = self.answers
        if answers is None:
            raise ValueError("no ik answers to show: the viewer has no ik result")
        i = int(np.clip(i, 0, len(answers.q) - 1))
        self._show_q(answers.q[i])
        for handle, pose in (
            (self._target_frame, answers.targets[i]),
            (self._reached_frame, answers.reached[i]),
        ):
            handle.visible = pose is not None
            if pose is not None:
                handle.position, handle.wxyz = tuple(pose[0]), tuple(pose[1])
        self._summary.content = answers.summary
        self._status.content = answers.text[i]
        if int(self._answer.value) != i:
            self._answer.value = i
        if self._live_gizmo is not None:
            self._place_gizmo()

    def _show_q(self, q: np.ndarray) -> None:
        self.q = np.asarray(q, dtype=float)
        self._show_geometry(*self._mesh.geometry(self.q)[:2])

    def _show_geometry(self, vertices: np.ndarray, lines: np.ndarray) -> None:
        with self.server.atomic():
            self._body.vertices = vertices.astype(np.float32)
            self._tendons.points = lines.astype(np.float32)

    # ------------------------------------------------------------ live IK
    def set_live(self, on: bool) -> None:
        """Turn live IK on (a target gizmo at the tip of the robot shown) or off.

        Raises:
            ValueError: the viewer was made with ``live_ik=False``.
        """
        if not hasattr(self, "_live_box"):
            raise ValueError("this viewer has no live IK (made with live_ik=False)")
        self._live_on = bool(on)
        if bool(self._live_box.value) != self._live_on:
            self._live_box.value = self._live_on
        if on and self._live_gizmo is None:
            self._live_gizmo = self.server.scene.add_transform_controls(
                "/live/target", scale=0.35, depth_test=False
            )
            self._place_gizmo()

            @self._live_gizmo.on_update
            async def _(event: Any) -> None:
                # On viser's event loop, so poses arrive in the drag's order; the solving
                # thread takes the newest. The slow fallback search only where a drag ends.
                self.target_moved(
                    event.target.position,
                    event.target.wxyz,
                    getattr(event, "phase", "end") == "end",
                )
        elif not on and self._live_gizmo is not None:
            self._live_gizmo.remove()
            self._live_gizmo = None
            if self._motion is not None:
                self.show_frame(self._frame)
            elif self.answers is not None:
                self.show_answer(int(self._answer.value))

    def _place_gizmo(self) -> None:
        rod_tip = None if self._tension is None else self._tension.tip()
        position, wxyz = tip_pose(self.robot, self.q) if rod_tip is None else rod_tip
        self._live_gizmo.position, self._live_gizmo.wxyz = tuple(position), tuple(wxyz)

    def target_moved(self, position: Any, wxyz: Any, final: bool) -> None:
        """The gizmo's callback: queue the target pose (position (3,) m, wxyz (4,)) for
        the solving thread and return at once. A drag sends poses faster than they can
        be solved: only the newest waiting one is solved. ``final``: the drag ended, so
        a miss may run the slow fallback search."""
        self._pending = (np.array(position, float), np.array(wxyz, float), bool(final))
        self._wake.set()

    def _live_loop(self) -> None:
        """The solving thread: the newest queued target, one at a time."""
        while not self._stop.is_set():
            self._wake.wait(0.5)
            self._wake.clear()
            pose, self._pending = self._pending, None
            if pose is not None:
                with self._solve_lock:
                    self._live_update(*pose)

    def solver(self) -> Any:
        """The live-IK solver (``tasks.geometry.live_ik.LiveIKSolver``, or on the rod
        ``tasks.mechanics.live_ik.TensionLiveIKSolver``), built on first use."""
        if self._tension is not None:
            return self._tension.solver()
        with self._solver_lock:
            if self._live_solver is None:
                from ..tasks.geometry.live_ik import LiveIKSolver

                self._live_solver = LiveIKSolver(self.robot, self.scene)
            return self._live_solver

    def _warm_up(self) -> None:
        """Compile the live-IK program in the background, so the first drag is fast."""
        with self._solve_lock:
            self._live_text.content = "compiling the live-IK solver (once, cached on disk)…"
            try:
                if self._tension is not None:
                    seconds = self._tension.warm()
                    if self.last_live is None:  # the rest shape under the loads
                        self._show_geometry(*self._tension.geometry())
                        if self._live_gizmo is not None:
                            self._place_gizmo()
                else:
                    position, wxyz = tip_pose(self.robot, self.q)
                    seconds = self.solver().solve(self.q, position, wxyz, search=False).seconds
            except Exception as exc:  # shown, never fatal: the replay works without it
                if not self._stop.is_set():
                    self._live_text.content = f"live IK unavailable: {exc}"
                return
            if self.last_live is None and not self._stop.is_set():
                self._live_text.content = f"ready (first solve {seconds:.1f} s)"

    def move_target(
        self, position: Any, wxyz: Any, exact: bool | None = None, search: bool = True
    ) -> Any:
        """What moving the gizmo does: re-solve IK for the target pose from the answer
        on screen, show the new answer and its verdict; returns the ``LiveIKResult``
        (on the rod: the ``TensionLiveIKResult``, the orientation not a target; None for
        an invalid target, reported on the page).

        Args:
            position: (3,) target tip position, m.
            wxyz: (4,) target orientation, unit quaternion.
            exact: polish with Ipopt; None: the page's checkbox.
            search: fall back to the batched search when the warm start misses (the
                gizmo does so where a drag ends, not during it).
        """
        with self._solve_lock:
            return self._live_update(
                np.asarray(position, float), np.asarray(wxyz, float), search, exact
            )

    def _live_update(
        self, position: np.ndarray, wxyz: np.ndarray, search: bool, exact: bool | None = None
    ) -> Any:
        if exact is None:
            exact = bool(getattr(self, "_exact_box", None) and self._exact_box.value)
        try:
            if self._tension is not None:
                if exact:
                    raise ValueError("the rod's live IK has no exact stage")
                answer = self._tension.solve(position, search)
            else:
                answer = self.solver().solve(self.q, position, wxyz, exact=exact, search=search)
        except ValueError as exc:  # an unreachable or invalid target: say so, keep the robot
            if hasattr(self, "_live_text"):
                self._live_text.content = f"target rejected: {exc}"
            return None
        self.last_live = answer
        if self._tension is not None:
            self._show_geometry(*self._tension.geometry())
            if hasattr(self, "_live_text"):
                self._live_text.content = self._tension.text(answer)
            return answer
        self._show_q(answer.q)
        if hasattr(self, "_live_text"):
            self._live_text.content = live_text(answer)
        return answer

    # ------------------------------------------------------------ lifetime
    def wait(self) -> None:
        """Block until Ctrl-C, then stop the server."""
        try:
            while not self._stop.is_set():
                time.sleep(0.5)
        except KeyboardInterrupt:
            pass
        finally:
            self.stop()
            if self._warming is not None and self._warming.is_alive():
                print("waiting for the live-IK compile to finish…", file=sys.stderr)
                self._warming.join()

    def stop(self) -> None:
        """Stop the replay and solving threads and the server (the port is free
        afterwards)."""
        if self._stop.is_set():
            return
        self._stop.set()
        self._wake.set()
        if self._solving.is_alive() and self._solving is not threading.current_thread():
            self._solving.join(timeout=60)  # a solve in progress ends in milliseconds
        self.server.stop()

    def __enter__(self) -> Viewer:
        return self

    def __exit__(self, *_: Any) -> None:
        self.stop()
