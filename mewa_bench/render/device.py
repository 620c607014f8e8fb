"""Finding a Vulkan device for SAPIEN (SPEC sections 9-10), without importing sapien.

SAPIEN renders through Vulkan. On a machine with a GPU its own Vulkan driver (ICD) is used; on a
CPU-only machine Mesa's lavapipe is, which must be recent (Debian 12's Mesa 22.3 is too old; see
`.ci/install-vulkan`). Detection only reads the loader's ICD json files and a few device nodes, and
selects the driver through `VK_ICD_FILENAMES`, which the Vulkan loader reads when sapien creates its
instance: so `activate` must run before the first SAPIEN render system is made.
"""

from __future__ import annotations

import glob
import json
import os
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

from mewa_bench.extras import MissingExtra

CPU_KIND = "cpu (lavapipe)"
GPU_KIND = "gpu"
# Mesa 22.3's lavapipe reports Vulkan 1.1 and cannot run SAPIEN 3; recent ones report >= 1.3.
MIN_LAVAPIPE_API = (1, 3)
ICD_ENV_VARS = ("VK_DRIVER_FILES", "VK_ICD_FILENAMES")  # the loader prefers the first one
INSTALL_HINT = (
    "install the Vulkan loader and a recent lavapipe (Mesa 25 works) with `bash .ci/install-vulkan` "
    "from the mewa-bench repository, or by hand on Debian 12: add the bookworm-backports source, then "
    "`apt-get install libvulkan1 mesa-vulkan-drivers/bookworm-backports` "
    "(and `pip install 'mewa-bench[sapien]'`)"
)
SAPIEN_FEATURE = "SAPIEN mode (`--mode sapien`)"
# PCI vendor ids of /sys/class/drm/renderD*/device/vendor, by the Mesa driver names that serve them.
_MESA_GPU_VENDORS = {
    "radeon": "0x1002", "intel": "0x8086", "intel_hasvk": "0x8086", "nouveau": "0x10de",
    "virtio": "0x1af4",
}


class RenderUnavailable(RuntimeError):
    """No Vulkan device that SAPIEN can render with (the message says how to install one)."""


@dataclass(frozen=True)
class RenderDevice:
    """A Vulkan driver chosen for SAPIEN: `kind` is "cpu (lavapipe)" or "gpu"."""

    name: str
    driver: str
    kind: str
    icd: str
    api_version: str = ""

    @property
    def is_gpu(self) -> bool:
        """True for a hardware device."""
        return self.kind == GPU_KIND


def icd_search_dirs() -> list[Path]:
    """The folders the Vulkan loader searches for driver json files, in its order."""
    home = Path.home()
    config = [os.environ.get("XDG_CONFIG_HOME", str(home / ".config"))]
    config += os.environ.get("XDG_CONFIG_DIRS", "/etc/xdg").split(":")
    data = [os.environ.get("XDG_DATA_HOME", str(home / ".local" / "share"))]
    data += os.environ.get("XDG_DATA_DIRS", "/usr/local/share:/usr/share").split(":")
    roots = config + ["/etc"] + data
    return [Path(r) / "vulkan" / "icd.d" for r in roots if r]


def _read_icd(path: Path) -> tuple[str, str] | None:
    """(library_path, api_version) of an ICD json file, or None if it is not one."""
    try:
        icd = json.loads(path.read_text())["ICD"]
        return str(icd["library_path"]), str(icd.get("api_version", ""))
    except (OSError, ValueError, KeyError, TypeError):
        return None


def _api_tuple(version: str) -> tuple[int, ...]:
    """A version such as "1.4.305" as (1, 4, 305); parts that are not numbers count as 0."""
    return tuple(int(p) if p.isdigit() else 0 for p in version.split("."))


def _driver_name(library: str) -> str:
    """Short driver name from an ICD library path: "lvp", "radeon", "nvidia", ..."""
    base = os.path.basename(library)
    if "nvidia" in base.lower():
        return "nvidia"
    for prefix in ("libvulkan_", "libvk_"):
        if base.startswith(prefix):
            return base[len(prefix):].split(".")[0]
    return base.split(".")[0]


def _read_text(path: str) -> str:
    """A small text file's stripped content, or "" if it cannot be read."""
    try:
        return Path(path).read_text().strip()
    except OSError:
        return ""


def _nvidia_gpu_name() -> str | None:
    """Model of the first NVIDIA GPU the kernel driver exposes, or None."""
    for info in sorted(glob.glob("/proc/driver/nvidia/gpus/*/information")):
        for line in _read_text(info).splitlines():
            if line.startswith("Model:"):
                return line.split(":", 1)[1].strip()
    return "NVIDIA GPU" if glob.glob("/dev/nvidia[0-9]*") else None


def _render_node_vendors() -> set[str]:
    """PCI vendor ids of the DRM render nodes (/dev/dri/renderD*)."""
    nodes = glob.glob("/dev/dri/renderD*")
    return {_read_text(f"/sys/class/drm/{os.path.basename(n)}/device/vendor") for n in nodes}


def _device_for(icd: Path, vendors: set[str] | None = None) -> RenderDevice | None:
    """The usable device this ICD file would give, or None (no hardware, lavapipe too old)."""
    read = _read_icd(icd)
    if read is None:
        return None
    library, api = read
    driver = _driver_name(library)
    if driver == "lvp":
        if _api_tuple(api)[:2] < MIN_LAVAPIPE_API:
            return None
        return RenderDevice("llvmpipe", f"lavapipe (Vulkan {api})", CPU_KIND, str(icd), api)
    if driver == "nvidia":
        name = _nvidia_gpu_name()
        return RenderDevice(name, f"nvidia (Vulkan {api})", GPU_KIND, str(icd), api) if name else None
    vendor = _MESA_GPU_VENDORS.get(driver)
    present = _render_node_vendors() if vendors is None else vendors
    if vendor is not None and vendor in present:
        return RenderDevice(f"{driver} GPU", f"mesa {driver} (Vulkan {api})", GPU_KIND, str(icd), api)
    return None


def _explicit_icds() -> list[Path] | None:
    """ICD files named by the user in VK_DRIVER_FILES / VK_ICD_FILENAMES, or None if unset."""
    for var in ICD_ENV_VARS:
        value = os.environ.get(var, "").strip()
        if value:
            return [Path(p) for p in value.split(os.pathsep) if p]
    return None


def installed_icds() -> list[Path]:
    """Every ICD json file in the loader's search folders (first occurrence of a name wins)."""
    seen: dict[str, Path] = {}
    for folder in icd_search_dirs():
        for path in sorted(folder.glob("*.json")) if folder.is_dir() else []:
            seen.setdefault(path.name, path)
    return list(seen.values())


def find_render_device() -> RenderDevice | None:
    """The best Vulkan device for SAPIEN: a GPU's own driver, else a recent lavapipe, else None.

    ICD files named in VK_DRIVER_FILES or VK_ICD_FILENAMES are honoured (and nothing else is
    considered then). Cheap: reads json files and device nodes only, never loads a driver.
    """
    explicit = _explicit_icds()
    candidates = explicit if explicit is not None else installed_icds()
    vendors = _render_node_vendors()
    devices = [d for d in (_device_for(p, vendors) for p in candidates) if d is not None]
    gpus = [d for d in devices if d.is_gpu]
    return (gpus or devices or [None])[0]


def activate(device: RenderDevice) -> None:
    """Point the Vulkan loader at this device's driver only (before sapien creates its instance)."""
    os.environ.pop("VK_DRIVER_FILES", None)  # it would take precedence over VK_ICD_FILENAMES
    os.environ["VK_ICD_FILENAMES"] = device.icd


_PROBE = """
import sapien, sapien.render as r
r.RenderSystem()
print(r.get_device_summary().splitlines()[0].partition(":")[2].strip())
"""


def probe_render_device(device: RenderDevice, timeout: float = 60.0) -> str:
    """Create a SAPIEN render system on `device` in a subprocess; return the device's name.

    Raises RenderUnavailable with SAPIEN's own error if it fails. Costs about a second.
    """
    env = {**os.environ, "VK_ICD_FILENAMES": device.icd}
    env.pop("VK_DRIVER_FILES", None)
    try:
        out = subprocess.run([sys.executable, "-c", _PROBE], env=env, capture_output=True,
                             text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        raise RenderUnavailable(f"SAPIEN did not start on {device.driver} within {timeout:.0f} s") from None
    if out.returncode != 0:
        tail = (out.stderr.strip().splitlines() or ["(no output)"])[-1]
        raise RenderUnavailable(f"SAPIEN cannot render on {device.driver} ({device.icd}): {tail}; {INSTALL_HINT}")
    return out.stdout.strip().splitlines()[-1] if out.stdout.strip() else device.name


def _sapien_installed() -> bool:
    import importlib.util

    return importlib.util.find_spec("sapien") is not None


_active: RenderDevice | None = None


def require_render_device(probe: bool = False) -> RenderDevice:
    """The device SAPIEN will use, activated; raise RenderUnavailable (with install steps) if none.

    With `probe`, also check in a subprocess that SAPIEN really starts on it (about a second).
    The first device chosen in a process stays chosen: SAPIEN creates its Vulkan instance once.
    """
    global _active
    if _active is not None:
        return _active
    if not _sapien_installed():
        raise RenderUnavailable(str(MissingExtra("sapien", "sapien", SAPIEN_FEATURE)))
    device = find_render_device()
    if device is None:
        named = _explicit_icds()
        where = f"in {', '.join(map(str, named))}" if named is not None else "on this machine"
        raise RenderUnavailable(f"no Vulkan driver that SAPIEN can render with {where}: {INSTALL_HINT}")
    if probe:
        device = RenderDevice(probe_render_device(device), device.driver, device.kind, device.icd,
                              device.api_version)
    activate(device)
    _active = device
    return device
