"""Options several commands share: their help texts, and parsing them (seeds, pairs, sizes, --mode, --ray)."""

from __future__ import annotations

import typer

from mewa_bench.cli.typer_app import _print_error

RAY_HELP = "Run the units as Ray tasks on a local Ray instance (needs the ray extra; --jobs caps its CPUs)."
RAY_ADDRESS_HELP = ("Run the units as Ray tasks on the Ray cluster at this address (e.g. 10.0.0.5:6379 or auto); "
                    "nodes need mewa-bench and the agent file at the same path.")


def _ray_option(ray: bool, address: str | None) -> str | None:
    """EvalConfig.ray from --ray / --ray-address (None: local processes), failing early without Ray."""
    if not ray and address is None:
        return None
    from mewa_bench.protocol.ray_backend import LOCAL, RayUnavailable, import_ray

    try:
        import_ray()
    except RayUnavailable as e:
        raise typer.BadParameter(str(e), param_hint="--ray") from None
    return address or LOCAL


def _mode_options(mode: str, image_size: str) -> dict:
    """Validate --mode and --image-size; in sapien mode check the render device before anything runs."""
    if mode not in ("vector", "sapien"):
        raise typer.BadParameter("expected vector or sapien", param_hint="--mode")
    try:
        height, width = (int(v) for v in image_size.lower().split("x"))
    except ValueError:
        raise typer.BadParameter(f"expected HxW such as 128x128, got {image_size!r}", param_hint="--image-size") from None
    if mode == "sapien":
        from mewa_bench.render.device import RenderUnavailable, require_render_device

        try:
            require_render_device()
        except RenderUnavailable as e:
            _print_error(e)
            raise typer.Exit(1) from None
    return {"mode": mode, "image_size": (height, width)}


def _parse_ints(text: str, option: str) -> list[int]:
    try:
        return [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise typer.BadParameter(f"expected integers separated by commas, got {text!r}", param_hint=option) from None


def _parse_seeds(text: str, option: str = "--seeds") -> tuple[int, ...]:
    values = _parse_ints(text, option)
    if "," not in text and len(values) == 1:
        if values[0] < 1:
            raise typer.BadParameter("a single number is a count of seeds (3 = seeds 0, 1, 2); for the one seed 0 "
                                     f"use {option} 1, for another one seed N use {option} N,", param_hint=option)
        return tuple(range(values[0]))
    return tuple(values)


def _parse_agent_args(items: list[str]) -> dict[str, str]:
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise typer.BadParameter(f"expected key=value, got {item!r}", param_hint="--agent-arg")
        out[key] = value
    return out


def _parse_bytes(text: str) -> int | None:
    if text.lower() in ("none", "0", ""):
        return None
    units = {"K": 1 << 10, "M": 1 << 20, "G": 1 << 30}
    try:
        if text[-1].upper() in units:
            return int(float(text[:-1]) * units[text[-1].upper()])
        return int(text)
    except ValueError:
        raise typer.BadParameter(f"expected a size like 4G, 512M or none, got {text!r}", param_hint="--memory-limit") from None
