"""A SAPIEN 3 scene of a MEWA game state (SPEC section 9): table, blocks, a fixed camera.

The scene is built once; `render` only moves, shows and hides blocks from pools made up front, so a
frame costs one rasterisation (a few ms at 128x128 on lavapipe). sapien is imported only when a
`SceneRenderer` is made, after the Vulkan driver has been chosen (see `device.py`).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from mewa_bench.extras import MissingExtra, require
from mewa_bench.game.rules import State
from mewa_bench.game.task import Task
from mewa_bench.render import layout
from mewa_bench.render.device import SAPIEN_FEATURE, RenderDevice, RenderUnavailable, require_render_device

# sRGB colours of the palette (orange, blue, green, red) and the worker's grey blocks.
BLOCK_SRGB = ((245, 130, 20), (30, 90, 225), (35, 165, 55), (215, 30, 30), (150, 150, 155))
TABLE_SRGB = (205, 195, 175)
PAD_SRGB = {"build": (150, 160, 180), "goal": (235, 240, 225), "worker": (95, 95, 105)}
FOV = math.radians(37.0)  # of the image's shorter side
CAMERA_PITCH = math.radians(52.0)  # looking down from the horizontal
CAMERA_TARGET = (-0.05, 0.0, 0.04)
CAMERA_DISTANCE = 1.5
SHADE = 0.7  # sRGB factor of the darker shade of odd tower levels
# Blocks made up front per (material, shade); more are made if a state needs them.
POOL_SIZES = {**{(c, 0): 9 for c in range(4)}, **{(c, 1): 3 for c in range(4)}, (layout.GREY, 0): 8}
PARKED = (0.0, 0.0, -1.0)  # under the table: where hidden blocks wait


def linear(srgb: tuple[float, ...], scale: float = 1.0) -> list[float]:
    """RGBA in linear light (what SAPIEN's materials take) from 8-bit sRGB, optionally darkened."""
    return [(scale * v / 255.0) ** 2.2 for v in srgb] + [1.0]


def look_quaternion(direction: tuple[float, float, float]) -> list[float]:
    """Quaternion (w, x, y, z) turning +x onto `direction` (SAPIEN lights and cameras look along +x)."""
    d = np.asarray(direction, dtype=np.float64)
    d /= np.linalg.norm(d)
    yaw, pitch = math.atan2(d[1], d[0]), -math.asin(d[2])
    cy, sy, cp, sp = math.cos(yaw / 2), math.sin(yaw / 2), math.cos(pitch / 2), math.sin(pitch / 2)
    return [cy * cp, -sy * sp, cy * sp, sy * cp]  # yaw about z after pitch about y


def _import_sapien() -> Any:
    """sapien, imported after the Vulkan driver is chosen."""
    try:
        return require("sapien", "sapien", SAPIEN_FEATURE)
    except MissingExtra as e:  # pragma: no cover - require_render_device checks it is installed
        raise RenderUnavailable(str(e)) from e


class _Block:
    """A pooled block: an entity with a box body, and where it is shown (None: hidden)."""

    __slots__ = ("entity", "body", "shown_at")

    def __init__(self, entity: Any, body: Any) -> None:
        self.entity, self.body = entity, body
        self.shown_at: tuple[float, ...] | None = None


class SceneRenderer:
    """Renders MEWA game states as uint8 [height, width, 3] images from a fixed camera.

    Deterministic: a state always gives the same bytes, whatever was rendered before and in any
    renderer of the same size. Raises RenderUnavailable if no Vulkan device can render.
    """

    def __init__(self, width: int = 128, height: int = 128) -> None:
        if int(width) < 1 or int(height) < 1:
            raise ValueError(f"image size must be positive, got {width}x{height}")
        self.width, self.height = int(width), int(height)
        self.device: RenderDevice = require_render_device()
        self._sapien = _import_sapien()
        self._render = self._sapien.render
        # A process-wide SAPIEN setting, read when a camera is made: 8-bit colour, no float copy.
        self._render.set_picture_format("Color", "r8g8b8a8unorm")
        try:
            self._scene = self._sapien.Scene([self._render.RenderSystem()])
        except RuntimeError as e:
            raise RenderUnavailable(f"SAPIEN cannot render on {self.device.driver} ({self.device.icd}): {e}") from e
        self._materials: dict[tuple[int, int], Any] = {}
        self._pools: dict[tuple[int, int], list[_Block]] = {}
        self._build_static()
        self._camera = self._build_camera()
        for key, count in POOL_SIZES.items():
            self._grow(key, count)

    def _material(self, rgba: list[float]) -> Any:
        """A matte material of one colour."""
        m = self._render.RenderMaterial()
        m.base_color = rgba
        m.roughness = 0.8
        m.metallic = 0.0
        m.specular = 0.2
        return m

    def _add_box(self, half: tuple[float, float, float], material: Any, pose: Any) -> tuple[Any, Any]:
        """Add an entity with one box, return (entity, render body)."""
        entity = self._sapien.Entity()
        body = self._render.RenderBodyComponent()
        body.attach(self._render.RenderShapeBox(list(half), material))
        entity.add_component(body)
        entity.set_pose(pose)
        self._scene.add_entity(entity)
        return entity, body

    def _build_static(self) -> None:
        """Table, the three area pads and the lights."""
        pose = self._sapien.Pose
        self._add_box((1.5, 1.5, 0.02), self._material(linear(TABLE_SRGB)), pose([0.0, 0.0, -0.02]))
        width = layout.LANE * layout.NUM_COLORS / 2
        margin = (layout.PITCH + layout.BLOCK) / 2
        pads = (("build", layout.X_BUILD, margin), ("goal", layout.X_GOAL, margin), ("worker", layout.X_WORKER, margin))
        for name, x, half_x in pads:
            self._add_box((half_x, width, 0.001), self._material(linear(PAD_SRGB[name])), pose([x, 0.0, 0.001]))
        self._scene.render_system.ambient_light = [0.35, 0.35, 0.35]
        for direction, strength in (((0.4, -0.5, -1.0), 0.9), ((-0.3, 0.6, -0.5), 0.35)):
            entity = self._sapien.Entity()
            light = self._render.RenderDirectionalLightComponent()
            light.color = [strength] * 3
            light.shadow = False  # on by default; a shadow pass would triple the frame time
            entity.add_component(light)
            entity.set_pose(pose([0, 0, 1], look_quaternion(direction)))
            self._scene.add_entity(entity)

    def _build_camera(self) -> Any:
        """The fixed camera, with a dummy BRDF look-up table (see below)."""
        entity = self._sapien.Entity()
        # The "minimal" shader (no environment lighting) is about twice as fast as "default".
        shaders = Path(self._sapien.__file__).parent / "vulkan_shader" / "minimal"
        camera = self._render.RenderCameraComponent(self.width, self.height, str(shaders))
        if self.width < self.height:
            camera.set_fovx(FOV, compute_y=True)
        else:
            camera.set_fovy(FOV, compute_x=True)
        camera.near, camera.far = 0.05, 5.0
        entity.add_component(camera)
        c, s = math.cos(CAMERA_PITCH), math.sin(CAMERA_PITCH)
        eye = [CAMERA_TARGET[0] - CAMERA_DISTANCE * c, CAMERA_TARGET[1], CAMERA_TARGET[2] + CAMERA_DISTANCE * s]
        entity.set_pose(self._sapien.Pose(eye, [math.cos(CAMERA_PITCH / 2), 0.0, math.sin(CAMERA_PITCH / 2), 0.0]))
        self._scene.add_entity(entity)
        # Without an environment map the BRDF table only scales a zero term, but SAPIEN would
        # compute it on the CPU at the first picture (~30 s on lavapipe): give it a 1x1 one.
        lut = self._render.RenderTexture(np.zeros((1, 1, 4), np.float32), 2, "R32G32B32A32Sfloat")
        camera.set_texture("BRDFLUT", lut)
        return camera

    def _grow(self, key: tuple[int, int], count: int) -> None:
        """Add `count` hidden blocks of one (material, shade) to its pool."""
        if key not in self._pools:
            material, shade = key
            self._materials[key] = self._material(linear(BLOCK_SRGB[material], SHADE if shade else 1.0))
            self._pools[key] = []
        half = (layout.BLOCK / 2,) * 3
        for _ in range(count):
            entity, body = self._add_box(half, self._materials[key], self._sapien.Pose(PARKED))
            body.visibility = 0.0
            self._pools[key].append(_Block(entity, body))

    def _show(self, block: _Block, where: tuple[float, ...]) -> None:
        """Show a pooled block at (x, y, z, tilt), touching the engine only if it moved."""
        if block.shown_at == where:
            return
        if block.shown_at is None:
            block.body.visibility = 1.0
        x, y, z, tilt = where
        block.entity.set_pose(self._sapien.Pose([x, y, z], [math.cos(tilt / 2), math.sin(tilt / 2), 0.0, 0.0]))
        block.shown_at = where

    def _hide(self, block: _Block) -> None:
        """Hide a pooled block (and park it under the table)."""
        if block.shown_at is not None:
            block.body.visibility = 0.0
            block.entity.set_pose(self._sapien.Pose(PARKED))
            block.shown_at = None

    def _arrange(self, task: Task, state: State) -> None:
        """Show, move and hide the pooled blocks to draw `state`."""
        wanted: dict[tuple[int, int], list[tuple[float, ...]]] = {key: [] for key in self._pools}
        for b in layout.layout(task, state):
            wanted.setdefault((b.material, b.shade), []).append((b.x, b.y, b.z, b.tilt))
        for key, places in wanted.items():
            missing = len(places) - len(self._pools.get(key, ()))
            if missing > 0:
                self._grow(key, missing)
            pool = self._pools[key]
            for block, where in zip(pool, places):
                self._show(block, where)
            for block in pool[len(places):]:
                self._hide(block)

    def render(self, task: Task, state: State) -> np.ndarray:
        """The image of `state` in `task`: uint8 [height, width, 3] (RGB)."""
        self._arrange(task, state)
        self._scene.update_render()
        self._camera.take_picture()
        rgba = self._camera.get_picture("Color")
        return np.ascontiguousarray(rgba[..., :3])

    def close(self) -> None:
        """Release the scene (the renderer cannot be used afterwards)."""
        self._pools = {}
        self._camera = None
        self._scene = None
