"""The GIF of one trial, drawn by MuJoCo's offscreen renderer in a child process.

MuJoCo picks its OpenGL back end when it is imported, so each back end is tried in a fresh
interpreter running this module::

    python -m sim.cheetah.render FRAMES.npz OUT.gif CAPTION

``FRAMES.npz`` holds ``qpos`` (frames, nq) and ``start_x``; ``render_gif`` writes it, has the
child draw into ``<gif>.part`` and renames that to the GIF once it is whole. Its
child first binds itself to its parent (``_START``: Linux's parent-death signal, before any
heavy import), so a cancelled job's worker, terminated mid-drawing, leaves no child writing
its GIF.
"""

from __future__ import annotations

import argparse
import errno
import os
import signal
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np

VIDEO_FPS = 10
"""Frames per simulated second of the GIF (the reference filmed at 15)."""
VIDEO_SECONDS = 14.0
"""Length of the GIF: running, the short stall at 5 s and the first long stop at 10 s."""
STEPS_PER_SECOND = 100
"""Simulation steps per second (the model's 0.01 s step)."""
GL_BACKENDS = ("egl", "osmesa", "glfw")
"""Offscreen OpenGL back ends tried, in order."""
FRAME_HEIGHT, FRAME_WIDTH = 192, 256
"""GIF frame size in pixels."""
RENDER_TIMEOUT_S = 300
"""Longest a child may take to draw the GIF."""
WRITE_FAILED = 73
"""The child's exit code when it cannot write the GIF (sysexits' ``EX_CANTCREAT``); the last
line of its stderr is the error's number and words."""
PR_SET_PDEATHSIG = 1
"""Linux's prctl option: the signal a process gets when the one that started it ends."""
_START = """import os, runpy, sys
if sys.platform.startswith("linux"):
    import ctypes
    ctypes.CDLL(None, use_errno=True).prctl({option}, {signal})
if os.getppid() != {parent}:
    sys.exit("the process that started this render has ended")
runpy.run_module("sim.cheetah.render", run_name="__main__", alter_sys=True)
"""
"""The child's first lines: bound to its parent's life before it imports anything heavy
(gymnasium and MuJoCo take a second or more; a cancelled job's render had outlived its worker
that long)."""


def render_gif(path: Path, qpos: np.ndarray, start_x: float, caption: str) -> dict[str, Any]:
    """Render ``qpos`` (steps + 1, nq) to a GIF in a child process with an offscreen back end.

    Returns ``video`` (the file name, or None) and ``video_note`` (the back end used, or why
    none worked). A GIF that cannot be written (the disk full, the folder read-only) is not a
    missing back end: ``OSError`` is raised, as for any other file of the run. The child
    draws into ``<name>.part``, renamed to ``path`` once whole: no partial GIF stays.
    """
    seconds = min(VIDEO_SECONDS, (len(qpos) - 1) / STEPS_PER_SECOND)
    times = np.arange(0, seconds, 1 / VIDEO_FPS)
    frames = np.unique(np.ceil(times * STEPS_PER_SECOND).astype(int))
    source = path.with_suffix(".npz")
    partial = path.with_name(path.name + ".part")
    try:
        np.savez(source, qpos=qpos[frames], start_x=np.array(start_x))
        backend, reasons = _draw_in_child(source, partial, caption)
        if backend is None:
            return {"video": None, "video_note": "no offscreen OpenGL context: " + reasons}
        partial.replace(path)
        return {"video": path.name, "video_note": f"rendered with MUJOCO_GL={backend}"}
    finally:
        source.unlink(missing_ok=True)
        partial.unlink(missing_ok=True)


def _draw_in_child(source: Path, target: Path, caption: str) -> tuple[str | None, str]:
    """Draw ``target`` in a child process, one back end after another: the back end that drew
    it, or None and why each failed. ``OSError`` when the child could not write it."""
    reasons = []
    for backend in GL_BACKENDS:
        start = _START.format(
            option=PR_SET_PDEATHSIG, signal=int(signal.SIGKILL), parent=os.getpid()
        )
        try:
            done = subprocess.run(
                [
                    *(sys.executable, "-c", start),
                    *(str(source), str(target), caption),
                ],
                env=_child_env(backend),
                capture_output=True,
                text=True,
                timeout=RENDER_TIMEOUT_S,
                check=False,
            )
        except (OSError, subprocess.SubprocessError) as exc:
            reasons.append(str(exc))
            break
        if done.returncode == 0 and target.is_file():
            return backend, ""
        last = (done.stderr.strip().splitlines() or ["no output"])[-1]
        if done.returncode == WRITE_FAILED:  # another back end would not help
            number, _, words = last.partition(" ")
            code = int(number) if number.isdigit() else errno.EIO
            raise OSError(code, words or os.strerror(code), str(target.with_suffix("")))
        reasons.append(f"{backend}: {last}")
    return None, "; ".join(reasons)


def _child_env(backend: str) -> dict[str, str]:
    """The current environment with MUJOCO_GL (and PyOpenGL's platform) set to ``backend``."""
    env = dict(os.environ)
    env["MUJOCO_GL"] = backend
    env["SRD_CHEETAH_RENDER_CHILD"] = "1"  # sim.cheetah leaves its MUJOCO_GL as set here
    if backend in ("egl", "osmesa"):
        env["PYOPENGL_PLATFORM"] = backend
    project_root = str(Path(__file__).resolve().parents[2])
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [project_root, env.get("PYTHONPATH")]))
    return env


def draw_gif(source: Path, target: Path, caption: str) -> None:
    """Draw every stored frame from the tracking camera, captioned with its time; save a GIF."""
    import mujoco  # here, not at the top: the child binds itself to its parent first
    from PIL import Image, ImageDraw

    from sim.cheetah.world import build_model

    stored = np.load(source)
    model = build_model(float(stored["start_x"]))
    data = mujoco.MjData(model)
    images = []
    with mujoco.Renderer(model, height=FRAME_HEIGHT, width=FRAME_WIDTH) as renderer:
        for frame, q in enumerate(stored["qpos"]):
            data.qpos[:] = q
            mujoco.mj_forward(model, data)
            renderer.update_scene(data, camera="track")
            # Software GL draws shadows and floor reflections slowly; the gait reads without.
            renderer.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = False
            renderer.scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = False
            image = Image.fromarray(renderer.render())
            ImageDraw.Draw(image).text(
                (4, 4), f"{caption}  t={frame / VIDEO_FPS:4.1f}s", fill=(0, 0, 0)
            )
            images.append(image.convert("P", palette=Image.Palette.ADAPTIVE, colors=64))
    try:
        images[0].save(
            target,
            format="GIF",
            save_all=True,
            append_images=images[1:],
            duration=int(1000 / VIDEO_FPS),
            loop=0,
        )
    except OSError as exc:  # the disk full, say: the parent says so (it is no back end's fault)
        print(f"{exc.errno or errno.EIO} {exc.strerror or exc}", file=sys.stderr)
        raise SystemExit(WRITE_FAILED) from exc


def main(argv: list[str] | None = None) -> None:
    """Command-line entry of the child process."""
    parser = argparse.ArgumentParser(
        prog="python -m sim.cheetah.render", description="Draw stored half-cheetah frames to a GIF."
    )
    parser.add_argument("source", type=Path, help="frames file written by render_gif (.npz)")
    parser.add_argument("target", type=Path, help="GIF to write")
    parser.add_argument("caption", help="text drawn on every frame before the time")
    args = parser.parse_args(argv)
    draw_gif(args.source, args.target, args.caption)


if __name__ == "__main__":
    main()
