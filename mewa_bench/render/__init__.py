"""SAPIEN-rendered images of MEWA states (SPEC section 9).

Importing this package is cheap and never imports sapien: that happens when a `SceneRenderer` is
made, after `require_render_device` has chosen the Vulkan driver (a GPU's, else lavapipe).
"""

from mewa_bench.render.device import (
    RenderDevice,
    RenderUnavailable,
    find_render_device,
    require_render_device,
)
from mewa_bench.render.scene import SceneRenderer

__all__ = ["RenderDevice", "RenderUnavailable", "SceneRenderer", "find_render_device", "require_render_device"]
