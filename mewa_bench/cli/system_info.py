"""What `mewa-bench info` reports: package versions, the evaluation protocol, env ids, Python and platform.

Protocol versions are numbered on their own (protocol 1, protocol 2), not by the package version: a
results file records both, and only the protocol decides whether results are ranked together.
"""

from __future__ import annotations

import platform
import sys
from importlib import metadata

KEY_PACKAGES = ("numpy", "scipy", "gymnasium", "typer", "rich", "mcap", "rerun-sdk", "lerobot", "torch", "sapien")


def package_version(name: str) -> str:
    """Installed version of a distribution, or 'not installed' (read from metadata, nothing imported)."""
    try:
        return metadata.version(name)
    except metadata.PackageNotFoundError:
        return "not installed"


def system_info() -> dict[str, str]:
    """Versions and platform facts, in display order."""
    from mewa_bench import __version__
    from mewa_bench.envs.registration import ENV_IDS
    from mewa_bench.protocol.results import PROTOCOL_VERSION, SCHEMA_VERSION

    info = {"mewa-bench": __version__, "protocol": f"{PROTOCOL_VERSION} (results schema {SCHEMA_VERSION})",
            "env ids": ", ".join(ENV_IDS)}
    info.update({name: package_version(name) for name in KEY_PACKAGES})
    info["python"] = f"{platform.python_version()} ({sys.executable})"
    info["platform"] = platform.platform()
    info["machine"] = f"{platform.machine()}, {_cpu_count()} CPUs"
    info["render device"] = render_device_text()
    return info


def render_device_text() -> str:
    """The Vulkan device SAPIEN mode would use, or why there is none (sapien is not imported)."""
    from mewa_bench.render.device import find_render_device

    device = find_render_device()
    if device is None:
        return "none usable (sapien mode unavailable: run `bash .ci/install-vulkan`)"
    return f"{device.name} ({device.kind}, Vulkan {device.api_version}, {device.icd})"


def _cpu_count() -> int:
    from mewa_bench.protocol.results import available_cpus

    return available_cpus()
