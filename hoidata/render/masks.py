"""Label maps and amodal masks for build-sdf's records: the passes of ``Renderer.masks``, drawn in one framebuffer.

:meth:`hoidata.render.Renderer.masks` makes one pyrender SEG pass for the visible label map and one more per
mesh for its amodal mask, each with its own scene upload, framebuffer resolve, depth and colour read-back and
depth linearisation. :class:`MaskRenderer` draws the same triangles with the same GL program (pyrender's own
``segmentation.vert`` / ``segmentation.frag``, compiled by pyrender's shader cache), the same uniforms (pyrender's
projection matrix for the intrinsics, the same view and model matrices), the same state (depth test ``GL_LESS``
on a 24-bit depth buffer, back faces culled, multisampling off on a 4-sample framebuffer resolved by a blit)
into the channels of one framebuffer: the label pass writes red (label / 255), then for mesh i the depth buffer
is cleared and the mesh drawn alone into channel i + 1 (green, blue, alpha). One read-back gives everything.

A pixel is covered in a pass exactly when a fragment passes the depth test, in both implementations, so the
masks are the same; the one possible difference is the order in which the label pass draws the meshes where
two of them have the very same 24-bit depth at a pixel centre: here in the order given (the first one wins),
in pyrender in the order of a Python set of scene nodes (which varies from process to process).
tests/test_render.py compares the two on posed toy hands and objects.
"""

from __future__ import annotations

import ctypes
import os

import numpy as np

from hoidata.render.renderer import CV_TO_GL, ZFAR, ZNEAR, RenderMesh, pyrender_intrinsics

MAX_MESHES = 3  # amodal masks live in the green, blue and alpha channels
MAX_LABEL = 255  # visible labels live in the red channel


class MaskRenderer:
    """One offscreen EGL context of ``width`` x ``height`` pixels for :meth:`masks`.

    Use as a context manager or call :meth:`close`. Not thread-safe: one MaskRenderer per thread. Closing it
    leaves other renderers working. Closing (or garbage-collecting) a pyrender-based
    :class:`~hoidata.render.Renderer` terminates the process's EGL display and with it every context on it
    (pyrender's behaviour); a MaskRenderer then makes itself a new context on its next call.
    """

    def __init__(self, width: int, height: int, znear: float = ZNEAR, zfar: float = ZFAR):
        from OpenGL import GL

        self.width, self.height = int(width), int(height)
        self.znear, self.zfar = float(znear), float(zfar)
        self._GL, self._closed = GL, False
        self._create()

    def _create(self) -> None:
        """A context with the program, the framebuffers and the mesh slots, current."""
        from pyrender.platforms import egl
        from pyrender.shader_program import ShaderProgramCache

        device = egl.get_device_by_index(int(os.environ.get("EGL_DEVICE_ID", "0")))
        self._platform = egl.EGLPlatform(self.width, self.height, device=device)
        self._platform.init_context()
        self._platform.make_current()
        self._programs = ShaderProgramCache()
        # without normals pyrender puts the instance matrix right after the positions: location 1
        self._program = self._programs.get_program("segmentation.vert", "segmentation.frag", defines={"INST_M_LOC": 1})
        self._program._add_to_context()
        self._renderbuffers, self._fb_ms, self._fb = _framebuffers(self.width, self.height)
        self._slots = [_MeshSlot() for _ in range(MAX_MESHES)]
        self._fixed_state()

    def _fixed_state(self) -> None:
        """pyrender's SEG-pass state and the fixed uniforms (view, model), set once: the context is this
        renderer's alone, so they stay as set from one frame to the next (only the projection and colour change)."""
        GL = self._GL
        GL.glViewport(0, 0, self.width, self.height)
        GL.glEnable(GL.GL_DEPTH_TEST)
        GL.glDepthMask(GL.GL_TRUE)
        GL.glDepthFunc(GL.GL_LESS)
        GL.glDepthRange(0.0, 1.0)
        GL.glClearColor(0.0, 0.0, 0.0, 0.0)
        GL.glDisable(GL.GL_MULTISAMPLE)
        GL.glEnable(GL.GL_CULL_FACE)
        GL.glCullFace(GL.GL_BACK)
        GL.glEnable(GL.GL_BLEND)
        GL.glBlendFunc(GL.GL_ONE, GL.GL_ZERO)
        GL.glPolygonMode(GL.GL_FRONT_AND_BACK, GL.GL_FILL)
        self._program._bind()
        self._program.set_uniform("V", np.linalg.inv(CV_TO_GL))  # what pyrender computes from the camera pose
        self._program.set_uniform("M", np.eye(4))
        self._color = GL.glGetUniformLocation(self._program._program_id, "color")
        self._program._unbind()

    def _current(self) -> bool:
        """Make the context current; False when the EGL display was terminated (by a pyrender Renderer's close
        or garbage collection), which took this context and everything in it along."""
        from OpenGL import error

        try:
            self._platform.make_current()
            return True
        except (AssertionError, error.Error):
            return False

    def close(self) -> None:
        """Release the GL objects and the context (idempotent)."""
        if self._closed:
            return
        from OpenGL import EGL

        GL, self._closed = self._GL, True
        if not self._current():  # the display was terminated: the context and its objects are gone already
            return
        for slot in self._slots:
            slot.delete()
        self._programs.clear()
        GL.glDeleteFramebuffers(2, [self._fb_ms, self._fb])
        GL.glDeleteRenderbuffers(len(self._renderbuffers), self._renderbuffers)
        # only this context: pyrender's delete_context also terminates the EGL display, which every other
        # renderer of the process shares (a pyrender Renderer closed that way breaks the others)
        display, context = self._platform._egl_display, self._platform._egl_context
        EGL.eglMakeCurrent(display, EGL.EGL_NO_SURFACE, EGL.EGL_NO_SURFACE, EGL.EGL_NO_CONTEXT)
        EGL.eglDestroyContext(display, context)

    def __enter__(self) -> "MaskRenderer":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def masks(self, K: np.ndarray, meshes: list[RenderMesh]) -> tuple[np.ndarray, np.ndarray]:
        """Visible label map (H, W) int32 and amodal masks (len(meshes), H, W) bool, as ``Renderer.masks``.

        ``K`` (3, 3) OpenCV intrinsics; at most MAX_MESHES meshes, labels 0..MAX_LABEL."""
        if self._closed:
            raise ValueError("MaskRenderer is closed")
        if len(meshes) > MAX_MESHES or any(not 0 <= m.label <= MAX_LABEL for m in meshes):
            raise ValueError(f"MaskRenderer draws at most {MAX_MESHES} meshes with labels 0..{MAX_LABEL}, got "
                             f"{len(meshes)} with labels {[m.label for m in meshes]}")
        from pyrender import IntrinsicsCamera

        GL = self._GL
        P = IntrinsicsCamera(*pyrender_intrinsics(K), znear=self.znear, zfar=self.zfar).get_projection_matrix(
            self.width, self.height)
        if not self._current():
            self._create()  # a new context on the re-initialised display
        try:
            for slot, mesh in zip(self._slots, meshes):
                slot.upload(mesh.vertices, mesh.faces)
            self._begin(P)
            GL.glColorMask(GL.GL_TRUE, GL.GL_FALSE, GL.GL_FALSE, GL.GL_FALSE)
            for slot, mesh in zip(self._slots, meshes):  # the visible label map, depth-tested, into red
                self._draw(slot, (mesh.label / 255.0, 0.0, 0.0))
            for i, slot in enumerate(self._slots[:len(meshes)]):  # each mesh alone into its own channel
                GL.glClear(GL.GL_DEPTH_BUFFER_BIT)
                GL.glColorMask(*(GL.GL_TRUE if c == i + 1 else GL.GL_FALSE for c in range(4)))
                self._draw(slot, (1.0, 1.0, 1.0))
            GL.glColorMask(GL.GL_TRUE, GL.GL_TRUE, GL.GL_TRUE, GL.GL_TRUE)
            self._program._unbind()
            GL.glFlush()
            rgba = self._read()
        finally:
            self._platform.make_uncurrent()
        amodal = np.moveaxis(rgba[..., 1:1 + len(meshes)] > 0, -1, 0)
        return rgba[..., 0].astype(np.int32), np.ascontiguousarray(amodal)

    def _begin(self, P: np.ndarray) -> None:
        """Bind the framebuffer and program, clear, and set the projection (the rest is :meth:`_fixed_state`)."""
        GL = self._GL
        GL.glBindFramebuffer(GL.GL_DRAW_FRAMEBUFFER, self._fb_ms)
        GL.glColorMask(GL.GL_TRUE, GL.GL_TRUE, GL.GL_TRUE, GL.GL_TRUE)
        GL.glClear(GL.GL_COLOR_BUFFER_BIT | GL.GL_DEPTH_BUFFER_BIT)
        self._program._bind()
        self._program.set_uniform("P", P)

    def _draw(self, slot: "_MeshSlot", color) -> None:
        GL = self._GL
        GL.glUniform3fv(self._color, 1, np.asarray(color, dtype=np.float32))  # as pyrender's set_uniform sends it
        GL.glBindVertexArray(slot.vao)
        GL.glDrawElementsInstanced(GL.GL_TRIANGLES, slot.n_indices, GL.GL_UNSIGNED_INT, ctypes.c_void_p(0), 1)
        GL.glBindVertexArray(0)

    def _read(self) -> np.ndarray:
        """(H, W, 4) uint8, rows from the top, after resolving the multisampled buffer as pyrender does."""
        GL = self._GL
        GL.glBindFramebuffer(GL.GL_READ_FRAMEBUFFER, self._fb_ms)
        GL.glBindFramebuffer(GL.GL_DRAW_FRAMEBUFFER, self._fb)
        GL.glBlitFramebuffer(0, 0, self.width, self.height, 0, 0, self.width, self.height,
                             GL.GL_COLOR_BUFFER_BIT, GL.GL_LINEAR)
        GL.glBindFramebuffer(GL.GL_READ_FRAMEBUFFER, self._fb)
        data = GL.glReadPixels(0, 0, self.width, self.height, GL.GL_RGBA, GL.GL_UNSIGNED_BYTE)
        GL.glBindFramebuffer(GL.GL_READ_FRAMEBUFFER, 0)
        GL.glBindFramebuffer(GL.GL_DRAW_FRAMEBUFFER, 0)
        return np.frombuffer(data, np.uint8).reshape(self.height, self.width, 4)[::-1]


class _MeshSlot:
    """A vertex array with its position, identity-instance and index buffers, refilled per frame."""

    def __init__(self):
        from OpenGL import GL

        self.vao = GL.glGenVertexArrays(1)
        self.buffers = list(GL.glGenBuffers(3))
        positions, instance, indices = self.buffers
        self.n_indices = 0
        GL.glBindVertexArray(self.vao)
        GL.glBindBuffer(GL.GL_ARRAY_BUFFER, positions)
        GL.glVertexAttribPointer(0, 3, GL.GL_FLOAT, GL.GL_FALSE, 12, ctypes.c_void_p(0))
        GL.glEnableVertexAttribArray(0)
        GL.glBindBuffer(GL.GL_ARRAY_BUFFER, instance)
        eye = np.ascontiguousarray(np.eye(4, dtype=np.float32).ravel())
        GL.glBufferData(GL.GL_ARRAY_BUFFER, eye.nbytes, eye, GL.GL_STATIC_DRAW)
        for column in range(4):  # the instance matrix, one vec4 attribute per column, as pyrender lays it out
            GL.glEnableVertexAttribArray(1 + column)
            GL.glVertexAttribPointer(1 + column, 4, GL.GL_FLOAT, GL.GL_FALSE, 64, ctypes.c_void_p(16 * column))
            GL.glVertexAttribDivisor(1 + column, 1)
        GL.glBindBuffer(GL.GL_ELEMENT_ARRAY_BUFFER, indices)
        GL.glBindVertexArray(0)

    def upload(self, vertices: np.ndarray, faces: np.ndarray) -> None:
        """Float32 positions (as pyrender casts them) and uint32 triangle indices."""
        from OpenGL import GL

        positions = np.ascontiguousarray(np.asarray(vertices, dtype=np.float32).ravel())
        indices = np.ascontiguousarray(np.asarray(faces, dtype=np.uint32).ravel())
        GL.glBindVertexArray(self.vao)
        GL.glBindBuffer(GL.GL_ARRAY_BUFFER, self.buffers[0])
        GL.glBufferData(GL.GL_ARRAY_BUFFER, positions.nbytes, positions, GL.GL_DYNAMIC_DRAW)
        GL.glBufferData(GL.GL_ELEMENT_ARRAY_BUFFER, indices.nbytes, indices, GL.GL_DYNAMIC_DRAW)
        GL.glBindVertexArray(0)
        self.n_indices = int(indices.size)

    def delete(self) -> None:
        from OpenGL import GL

        GL.glDeleteVertexArrays(1, [self.vao])
        GL.glDeleteBuffers(len(self.buffers), self.buffers)


def _framebuffers(width: int, height: int) -> tuple[list, int, int]:
    """(renderbuffers, 4-sample framebuffer, single-sample framebuffer): RGBA colour and 24-bit depth each,
    as pyrender's offscreen framebuffers."""
    from OpenGL import GL

    buffers = list(GL.glGenRenderbuffers(4))
    framebuffers = []
    for samples, (color, depth) in ((4, buffers[:2]), (0, buffers[2:])):
        for buffer, fmt in ((color, GL.GL_RGBA), (depth, GL.GL_DEPTH_COMPONENT24)):
            GL.glBindRenderbuffer(GL.GL_RENDERBUFFER, buffer)
            if samples:
                GL.glRenderbufferStorageMultisample(GL.GL_RENDERBUFFER, samples, fmt, width, height)
            else:
                GL.glRenderbufferStorage(GL.GL_RENDERBUFFER, fmt, width, height)
        fb = GL.glGenFramebuffers(1)
        GL.glBindFramebuffer(GL.GL_DRAW_FRAMEBUFFER, fb)
        GL.glFramebufferRenderbuffer(GL.GL_DRAW_FRAMEBUFFER, GL.GL_COLOR_ATTACHMENT0, GL.GL_RENDERBUFFER, color)
        GL.glFramebufferRenderbuffer(GL.GL_DRAW_FRAMEBUFFER, GL.GL_DEPTH_ATTACHMENT, GL.GL_RENDERBUFFER, depth)
        framebuffers.append(fb)
    GL.glBindFramebuffer(GL.GL_DRAW_FRAMEBUFFER, 0)
    return buffers, framebuffers[0], framebuffers[1]
