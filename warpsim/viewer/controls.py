"""The control panel (viser front end): play / pause / single step / reset, speed, the frame,
simulated time and wall milliseconds per frame, Record / Stop, and the error box (also raised as a
notification over the 3D view of every open tab: seen wherever the panel is scrolled). Pause
answers at once (a frame being simulated stops after its sub-step under way); Reset shows the values
it runs with in every input and says what it restored.

Speed choices are simulated seconds per wall second; "real time" (1x) is the default and runs
as fast as the machine can when it cannot keep up; "max" never waits. The readout shows what
was achieved.
"""
from __future__ import annotations

import math
import threading

__all__ = ["SPEEDS", "Controls", "format_status"]

SPEEDS = {"0.25x": 0.25, "0.5x": 0.5, "1x (real time)": 1.0, "2x": 2.0, "4x": 4.0, "max": math.inf}


def format_status(status):
    """Markdown readout of ``Session.status()``."""
    state = "playing" if status["playing"] else ("failed" if status["error"] else "paused")
    where = "frame"
    if status.get("exploding"):
        state, where = "blowing up", "since frame"
    elif status["error"]:
        where = "at frame"
    text = (f"**{status['scene']}** {state}  \n{where} {status['frame']} | t = {status['time']:.3f} s  \n"
            f"{status['wall_ms']:.1f} ms/frame + {status.get('draw_ms', 0.0):.1f} ms/draw | "
            f"{status['sim_rate']:.3g} sim s per wall s")
    if status["grabbed"]:
        text += f"  \ndragging particle {status['grabbed']['particle']}"
    return text


class Controls:
    """Builds the control panel on ``viewer.server.gui`` and keeps its readouts current."""

    def __init__(self, viewer):
        self.viewer = viewer
        session = viewer.session
        gui = viewer.server.gui
        with gui.add_folder("Simulation"):
            self.status = gui.add_markdown(format_status(session.status()))
            self.play = gui.add_button("Pause" if session.playing else "Play")
            self.step = gui.add_button("Step")
            self.reset = gui.add_button("Reset")
            self.speed = gui.add_dropdown("Speed", list(SPEEDS), initial_value="1x (real time)")
            self.record = gui.add_button("Record")
            self.record_status = gui.add_markdown("not recording")
        self.error = gui.add_markdown("", visible=False)
        self.message = gui.add_markdown("")
        self._notices = {}  # client id -> the error notification shown over its 3D view
        self._notice_text = None
        self._notice_lock = threading.Lock()

        @self.play.on_click
        def _(_):
            session.set_playing(not session.playing)  # no lock: answers while a slow frame runs
            self.play.label = "Pause" if session.playing else "Play"

        @self.step.on_click
        def _(_):
            session.step_once()
            viewer.redraw()
            self.refresh()

        @self.reset.on_click
        def _(_):
            try:
                session.reset()
            except ValueError as exc:
                self.say(f"reset failed: {exc}")
            else:
                self.say(session.messages[-1][1] if session.messages else "reset to frame 0")
            handles = getattr(viewer, "param_handles", None)
            if handles:
                from .params import sync_param_handles

                sync_param_handles(handles, session)  # the values it runs with, in every tab
            viewer.redraw()
            self.refresh()

        @self.speed.on_update
        def _(_):
            session.speed = SPEEDS[self.speed.value]

        @self.record.on_click
        def _(_):
            if session.recorder is None:
                try:
                    path = session.start_recording()
                except (ValueError, OSError) as exc:
                    self.say(f"cannot record: {exc}")
                    return
                self.record.label = "Stop recording"
                self.record_status.content = f"recording into `{path}`"
            else:
                path = session.stop_recording()
                self.record.label = "Record"
                self.record_status.content = f"recorded `{path}`"
            self.refresh()

    def say(self, text):
        self.message.content = text

    def starting(self):
        """The readout while the first frame is stepped (its Warp kernels compile then, once per
        kernel cache: seconds to a minute on a CPU, the page otherwise silent)."""
        name = self.viewer.session.cls.name
        text = (f"**{name}** starting: compiling Warp's kernels and stepping frame 1 (once per kernel cache; "
                f"seconds to a minute on a CPU)")
        if self.status.content != text:
            self.status.content = text

    def _notify(self, text):
        """Show ``text`` (None: nothing) as the error notification of every open tab.

        A tab keeps one notification while there is an error: a new text (the blow-up shown, then
        the pause's explanation) updates its body in place, and it is removed once when the error
        goes. (Removing one and showing another within a few milliseconds could leave one drawn in
        the browser after its removal.)"""
        with self._notice_lock:
            if text == self._notice_text:
                return
            self._notice_text = text
            if text is None:
                for note in self._notices.values():
                    note.remove()
                self._notices = {}
                return
            for note in self._notices.values():
                note.body = self._notice_body(text)
            server = self.viewer.server
            if server is None:
                return
            for client_id, client in server.get_clients().items():
                if client_id not in self._notices:
                    self._notices[client_id] = self._add_notice(client, text)

    @staticmethod
    def _notice_body(text):
        return text.replace("**", "").replace("  \n", "\n")

    @staticmethod
    def _add_notice(client, text):
        return client.add_notification("Simulation error", Controls._notice_body(text),
                                       with_close_button=True, color="red")

    def on_connect(self, client):
        """A tab opened: it gets the error notification while there is one."""
        with self._notice_lock:
            if self._notice_text is not None and client.client_id not in self._notices:
                self._notices[client.client_id] = self._add_notice(client, self._notice_text)

    def on_disconnect(self, client):
        with self._notice_lock:
            self._notices.pop(client.client_id, None)

    def refresh(self):
        """Update the readouts from the session (called a few times a second)."""
        st = self.viewer.session.status()
        text = format_status(st)
        pace = getattr(self.viewer, "pace", None)
        note = pace.note() if pace is not None else None
        self.status.content = text + (f"  \n{note}" if note else "")
        label = "Pause" if st["playing"] else "Play"
        if self.play.label != label:
            self.play.label = label
        if st["recording"] is None and self.record.label != "Record":
            self.record.label = "Record"
            last = self.viewer.session.last_recording
            self.record_status.content = f"recorded `{last}`" if last else "not recording"
        elif st["recording"] is not None:
            self.record_status.content = f"recording into `{st['recording']}` ({st['recorded_frames']} frames)"
        handles = getattr(self.viewer, "param_handles", None)
        if handles:
            from .params import refresh_dt_limit

            refresh_dt_limit(handles, self.viewer.session)
        if st.get("exploding"):
            text = "**Simulation error**: blowing up (shown for a moment, then paused)"
            if self.error.content != text:
                self.error.content = text
                self.error.visible = True
            self._notify("blowing up (shown for a moment, then paused)")
        elif st["error"]:
            text = "**Simulation error** (paused; press Reset):  \n" + st["error"]
            if self.error.content != text:
                self.error.content = text
                self.error.visible = True
            self._notify("paused; press Reset.  \n" + st["error"])
        else:
            if self.error.visible:
                self.error.visible = False
            self._notify(None)
