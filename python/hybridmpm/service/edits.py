"""The edits of a running session between frames (:class:`SessionEdits`):
pours, obstacle moves, rigid bodies added and removed, and the bodies'
description.

:class:`~hybridmpm.service.core.SessionCore` is built on it: these are its
methods, written here so that the core keeps a session's life (steps, play,
controls, saves) and this module what changes a session's contents. Each
edit takes the session's lock, refuses a closed session
(:class:`~hybridmpm.service.core.SessionGoneError`), marks it changed (saved
like a step) and tells the viewers through the core's ``on_event`` hook.
"""

from __future__ import annotations

import dataclasses
import threading
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

from hybridmpm.errors import InvalidInputError
from hybridmpm.mpm import INTEGRATORS
from hybridmpm.mpm.bodies import Body
from hybridmpm.service.budget import Recording
from hybridmpm.service.facts import SessionFacts, session_integrator
from hybridmpm.service.schemas import clean
from hybridmpm.sim import Frame, RealtimeSimulator, Simulator


class SessionEdits:
    """The edits of a session between frames, as methods of
    :class:`~hybridmpm.service.core.SessionCore` (its base class; it sets
    what is declared here)."""

    lock: threading.RLock  # the simulator
    sim: Simulator
    facts: SessionFacts
    poured: bool  # particles were added (a reset then builds its simulator again)
    recording: Recording
    on_event: Callable[[dict[str, Any]], None]
    _held: threading.Lock  # the recording, the kept controls, the control flag

    if TYPE_CHECKING:  # the core's own, which the edits call

        @property
        def frame_index(self) -> int: ...

        def _open(self) -> None: ...

        def _changed(self) -> None: ...

        def _show(self, fr: Frame, control_frame: int = 0) -> None: ...

    def move_obstacle(self, index: int, center: list[float], velocity: list[float] | None) -> int:
        """Move obstacle ``index`` to ``center`` over the next step
        (:meth:`hybridmpm.sim.MpmSimulator.move_obstacle`; its errors name
        ``index``, ``center``, ``velocity``); the viewers get an ``obstacle``
        event. Returns the session's frame."""
        with self.lock:
            self._open()
            self.sim.move_obstacle(index, center, velocity)  # type: ignore[attr-defined] # MPM and hybrid (the route refuses the network alone)
            frame = self.frame_index
            self._changed()  # a pending move is part of the state: saved like a step
        self.on_event({"type": "obstacle", "index": int(index), "center": [float(x) for x in center]})
        return frame

    def _water_only(self, what: str) -> None:
        """Refuse ``what`` (an edit that would put something besides water in the box) on a session whose MPM
        is not the explicit one: the projection steps water only, so every later step would be
        refused. :class:`InvalidInputError` naming ``integrator``; the session unchanged. A real-time session
        takes it: its simulator moves to the explicit step (:class:`~hybridmpm.sim.RealtimeSimulator`)."""
        integrator = session_integrator(self.sim)
        if integrator != INTEGRATORS[0] and not isinstance(self.sim, RealtimeSimulator):
            raise InvalidInputError(
                f"integrator: this session's {integrator} integrator steps water only, so it takes no {what}; "
                f"create the session with integrator '{INTEGRATORS[0]}'",
                "integrator",
            )

    def pour(self, block: dict[str, Any]) -> dict[str, Any]:
        """Add ``block`` (a scene file's block: ``material``, its parameters,
        ``lo``, ``hi``, ``velocity``) between frames (:func:`hybridmpm.sim.pour.pour_block`;
        its errors name the field and leave the session unchanged; a session on
        the projection takes water only, :meth:`_water_only`). The recent
        trajectory starts again; the viewers get the frame and a ``particles``
        event with the new count and particle types. Returns ``{"added",
        "num_particles", "frame", "facts"}`` (``facts``: the session's new
        :class:`SessionFacts` as a dict, for a front end that keeps a copy)."""
        from hybridmpm.sim.pour import pour_block  # import time: loaded by a pour only

        with self.lock:
            self._open()
            if block.get("material") != "water":
                self._water_only(f"block of {block.get('material')!r}")
            before = self.facts.num_total
            pour_block(self.sim, block)
            self.facts = SessionFacts.of(self.sim)
            self.poured = True
            self._changed()
            with self._held:
                self.recording.clear()
            self._show(self.sim.frame)
            frame, facts = self.frame_index, self.facts
        added = facts.num_total - before
        self.on_event(
            {"type": "particles", "frame": frame, "added": added, "num_particles": facts.num_total, "num_fluid": facts.num_fluid,
             "particle_type": [int(t) for t in facts.particle_type]}
        )  # fmt: skip
        return {"added": added, "num_particles": facts.num_total, "frame": frame, "facts": facts.to_dict()}

    # ------------------------------------------------------------ rigid bodies
    def bodies_given(self) -> list[dict[str, Any]]:
        """The session's rigid bodies as given (a scene file's ``[[bodies]]``
        tables, added ones included, removed ones gone; docs/bodies.md), as
        JSON values; ``[]`` for a simulator without bodies (the learned ones)."""
        solver = getattr(self.sim, "solver", None)
        given = getattr(getattr(solver, "params", None), "bodies", None) or []
        return [clean({f.name: getattr(b, f.name) for f in dataclasses.fields(b) if getattr(b, f.name) is not None}) for b in given]

    def bodies_now(self) -> list[dict[str, Any]]:
        """Each body's shape and size as given (``half_extents``, ``radius``,
        a capsule's ``radius`` and ``half_height``; a mesh's hull as
        ``vertices`` [[x, y, z], ...] in the body's frame [m] and ``faces``
        [[i, j, k], ...], outward), its ``mass`` [kg; per unit depth in 2D]
        and its ``center`` (centre of mass), ``rotation``, ``velocity`` and
        ``angular_velocity`` at the current frame; ``[]`` without bodies."""
        for _ in range(3):  # read without the session's lock (a description never waits for a step): a body added meanwhile reads again
            given = self.bodies_given()
            if not given:
                return []
            b = self.sim.bodies  # type: ignore[attr-defined] # an MPM simulator: the others hold no bodies (bodies_given is empty)
            if len(b) == len(given) and self.bodies_given() == given:
                break
        else:  # changed under every read (bodies added or removed meanwhile): read once more under the lock, after the step
            with self.lock:
                given, b = self.bodies_given(), self.sim.bodies  # type: ignore[attr-defined]
        out: list[dict[str, Any]] = []
        for i, g in enumerate(given[: len(b)]):
            body: dict[str, Any] = {"shape": g["shape"], **{k: g[k] for k in ("half_extents", "radius", "half_height") if k in g}, "mass": float(b.mass[i])}
            if g["shape"] == "mesh":
                hull = Body.from_dict(g).hull()
                body["vertices"] = clean(np.asarray(hull["vertices"], np.float64).tolist())
                body["faces"] = np.asarray(hull["faces"], np.int64).tolist()
            for k in ("center", "rotation", "velocity", "angular_velocity"):
                body[k] = clean(np.asarray(getattr(b, k)[i], np.float64).tolist())
            out.append(body)
        return out

    def _bodies_event(self, frame: int) -> None:
        self.on_event({"type": "bodies", "frame": frame, "bodies": self.bodies_given()})

    def add_body(self, body: dict[str, Any]) -> dict[str, Any]:
        """Add rigid body ``body`` (a scene file's ``[[bodies]]`` table)
        between frames (:meth:`hybridmpm.sim.MpmSimulator.add_body`; its
        errors name the field, ``bodies[i].density``, and leave the session
        unchanged; the projection steps them too, docs/large-step.md); the viewers get a ``bodies`` event with every body as
        given. Returns ``{"index", "num_bodies", "frame", "facts"}``."""
        with self.lock:
            self._open()
            index = int(self.sim.add_body(body))  # type: ignore[attr-defined] # MPM only (the route refuses the others)
            self._changed()
            frame, num = self.frame_index, len(self.bodies_given())
            self._bodies_event(frame)
        return {"index": index, "num_bodies": num, "frame": frame, "facts": self.facts.to_dict()}

    def remove_body(self, index: int) -> dict[str, Any]:
        """Remove body ``index`` between frames (the later ones move down
        one; :meth:`hybridmpm.sim.MpmSimulator.remove_body`, its error names
        ``index``); the viewers get a ``bodies`` event. Returns ``{"index",
        "num_bodies", "frame", "facts"}``."""
        with self.lock:
            self._open()
            self.sim.remove_body(index)  # type: ignore[attr-defined] # MPM only (the route refuses the others)
            self._changed()
            frame, num = self.frame_index, len(self.bodies_given())
            self._bodies_event(frame)
        return {"index": int(index), "num_bodies": num, "frame": frame, "facts": self.facts.to_dict()}


__all__ = ["SessionEdits"]
