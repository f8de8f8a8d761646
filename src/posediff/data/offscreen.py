"""Offscreen OpenGL (pyrender over EGL) in a PyTorch process: what every posediff renderer shares.

Two traps of offscreen GL next to PyTorch are handled here (``../shared/docs/install-notes.md``):

* importing ``triton`` after a Mesa GL context exists segfaults — :func:`prepare_gl` imports it
  first (if installed);
* forked ``DataLoader`` workers hang if the parent made a GL context — :func:`prepare_gl` sets
  ``LP_NUM_THREADS=0`` (unless set), and renderers create their context lazily, in the process that
  renders.

:func:`prepare_gl` also makes ``PYOPENGL_PLATFORM`` default to ``egl`` (Mesa's software EGL on a CPU
machine, NVIDIA's on a GPU machine); set it yourself to override. Nothing is changed in the
environment when posediff is imported: only when a renderer is about to make its first GL context.
:func:`release` frees one pyrender ``OffscreenRenderer`` without terminating the process-wide EGL
display.
"""

from __future__ import annotations

import logging
import os
from typing import Any

import numpy as np

#: OpenCV camera frame (x right, y down, z forward) → OpenGL camera frame (y up, z backward).
CV_TO_GL = np.diag([1.0, -1.0, -1.0, 1.0])

_GL_READY = False

#: what to install for each platform PyOpenGL can render offscreen with (Debian / Ubuntu packages)
_PLATFORM_PACKAGES = {
    "egl": "libegl1 libegl-mesa0 libgl1-mesa-dri",
    "osmesa": "libosmesa6",
}


class OffscreenGLError(OSError):
    """No offscreen OpenGL on this machine with the chosen ``PYOPENGL_PLATFORM`` (its library is
    missing, or it cannot make a context). One line: the platform, the cause and what to do."""


def _gl_error(e: BaseException) -> OffscreenGLError:
    platform = os.environ.get("PYOPENGL_PLATFORM", "egl")
    detail = " ".join(str(a) for a in getattr(e, "args", ()) if a) or type(e).__name__
    detail = detail.replace("\n", " ")[:200]
    packages = _PLATFORM_PACKAGES.get(platform)
    fix = f"install {packages} (apt)" if packages else "it is not a platform posediff has been run on"
    other = "" if platform == "egl" else "; or unset PYOPENGL_PLATFORM to render with EGL, posediff's default"
    return OffscreenGLError(
        f"cannot render offscreen with PYOPENGL_PLATFORM={platform} ({type(e).__name__}: {detail}): {fix}{other}"
    )


def import_pyrender() -> Any:
    """``pyrender``, imported after :func:`prepare_gl`; a platform whose OpenGL library cannot be
    loaded (``PYOPENGL_PLATFORM=osmesa`` without libOSMesa, EGL without Mesa) is an
    :class:`OffscreenGLError` naming it, not PyOpenGL's 60-line traceback."""
    prepare_gl()
    try:
        import pyrender
    except (ImportError, AttributeError, OSError, RuntimeError) as e:
        raise _gl_error(e) from e
    return pyrender


def offscreen_renderer(width: int, height: int) -> Any:
    """A ``pyrender.OffscreenRenderer(width, height)``; a context that cannot be made is an
    :class:`OffscreenGLError`."""
    pyrender = import_pyrender()
    try:
        return pyrender.OffscreenRenderer(width, height)
    except (ImportError, AttributeError, OSError, RuntimeError, ValueError) as e:
        raise _gl_error(e) from e


def prepare_gl() -> None:
    """Make the process safe for an offscreen GL context (idempotent; call it before importing
    pyrender or OpenGL): the environment defaults ``PYOPENGL_PLATFORM=egl`` and ``LP_NUM_THREADS=0``
    (an existing value is kept), and ``import triton`` before any context exists."""
    global _GL_READY
    if _GL_READY:
        return
    os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
    os.environ.setdefault("LP_NUM_THREADS", "0")
    logging.getLogger("OpenGL").setLevel(logging.WARNING)  # "No OpenGL_accelerate module loaded"
    try:  # noqa: SIM105 — importing it later, after a GL context exists, segfaults
        import triton  # noqa: F401
    except Exception:  # pragma: no cover — not installed, or broken: nothing to protect against
        pass
    _GL_READY = True


def release(renderer: Any) -> None:
    """Free a pyrender ``OffscreenRenderer``.

    pyrender's own ``delete()`` ends with ``eglTerminate`` on the process-wide default EGL display,
    which breaks every other live renderer in the process; on EGL only this renderer's context is
    destroyed here (other platforms use ``delete()``)."""
    platform = getattr(renderer, "_platform", None)
    if platform is None:
        return
    if type(platform).__name__ != "EGLPlatform":
        renderer.delete()
        return
    from OpenGL.EGL import (
        EGL_DRAW,
        EGL_NO_CONTEXT,
        EGL_NO_SURFACE,
        EGL_READ,
        eglDestroyContext,
        eglGetCurrentContext,
        eglGetCurrentDisplay,
        eglGetCurrentSurface,
        eglMakeCurrent,
    )

    # this may run from a garbage-collected renderer's __del__ while another renderer is drawing:
    # make the other context current again afterwards, or its next GL call has no context
    previous = (eglGetCurrentDisplay(), eglGetCurrentSurface(EGL_DRAW), eglGetCurrentSurface(EGL_READ),
                eglGetCurrentContext())  # fmt: skip
    platform.make_current()
    renderer._renderer.delete()
    eglMakeCurrent(platform._egl_display, EGL_NO_SURFACE, EGL_NO_SURFACE, EGL_NO_CONTEXT)
    eglDestroyContext(platform._egl_display, platform._egl_context)
    if _handle(previous[3]) and _handle(previous[3]) != _handle(platform._egl_context):
        eglMakeCurrent(*previous)
    platform._egl_context = None
    platform._egl_display = None  # the platform's own __del__ would eglTerminate it
    renderer._renderer = None
    renderer._platform = None  # pyrender's __del__ then does nothing


def _handle(obj: Any) -> int:
    """The address behind an EGL handle (a ctypes pointer), for comparisons."""
    import ctypes

    if obj is None or isinstance(obj, int):
        return int(obj or 0)
    return int(ctypes.cast(obj, ctypes.c_void_p).value or 0)


__all__ = ["CV_TO_GL", "prepare_gl", "release"]
