"""The frame every page shares: head, style, navigation, and how numbers and times are shown."""

from __future__ import annotations

import html

from mewa_bench.service.jobs import utc_text

STYLE = """body{font-family:system-ui,sans-serif;color:#222;max-width:90em;margin:1.5em auto;padding:0 1em}
nav{margin-bottom:1em;font-size:.9em}nav a{margin-right:1em}
table{border-collapse:collapse;margin:.5em 0 1.5em;font-size:.9em}#ranking{font-size:.8em}
#ranking,#algorithms{font-size:.8em;max-width:100%}#ranking td,#ranking th,#algorithms td,#algorithms th{padding:.2em .3em}
#ranking td.n,#algorithms td.n{white-space:normal}
.source{white-space:nowrap}
th,td{border:1px solid #ccc;padding:.25em .6em;text-align:left;vertical-align:top}th{background:#f2f2f2}
td.n{text-align:right;font-variant-numeric:tabular-nums;white-space:nowrap}
tr.reference{color:#555;font-style:italic}tr.privileged{color:#654}
figure{margin:1em 0}figure img{max-width:100%;border:1px solid #ddd}figcaption{font-size:.85em;color:#555}
.status{display:inline-block;padding:.1em .6em;border-radius:.3em;font-weight:bold}
.status.done{background:#d7f2d7}.status.rejected,.status.failed{background:#f6d2d2}
.status.queued,.status.running{background:#fff1c2}
.reason{border-left:4px solid #c33;padding:.3em .8em;background:#fbeaea;white-space:pre-wrap}
.muted{color:#666;font-size:.9em}dt{font-weight:bold}dd{margin:0 0 .5em 1.5em}"""


def esc(value: object) -> str:
    """Text or an attribute value, escaped for HTML (quotes too)."""
    return html.escape(str(value), quote=True)


def page(title: str, body: str, refresh_seconds: int | None = None) -> str:
    """A whole HTML document; `refresh_seconds` makes the browser reload it (a page still changing)."""
    refresh = "" if refresh_seconds is None else f'<meta http-equiv="refresh" content="{int(refresh_seconds)}">'
    return (f'<!doctype html>\n<html lang="en"><head><meta charset="utf-8">{refresh}'
            f'<meta name="viewport" content="width=device-width, initial-scale=1">'
            f"<title>{esc(title)}</title><style>{STYLE}</style></head><body>\n"
            f'<nav><a href="/">MEWA benchmark service</a><a href="/docs">API</a>'
            f'<a href="/openapi.json">OpenAPI</a></nav>\n<h1>{esc(title)}</h1>\n{body}\n</body></html>\n')


def number(value: float | None, digits: int = 4) -> str:
    """A score with `digits` decimals, empty when absent."""
    return "" if value is None else f"{value:.{digits}f}"


def with_ci(estimate: dict | None) -> str:
    """`0.9512 [0.9401, 0.9600]` from an estimate dict {mean, low, high}; the bare mean without a CI."""
    if estimate is None:
        return ""
    if estimate.get("low") is None or estimate.get("high") is None:
        return number(estimate["mean"])
    return f"{estimate['mean']:.4f} [{estimate['low']:.4f}, {estimate['high']:.4f}]"


def utc(seconds: float | None) -> str:
    """Unix seconds as `2026-11-23 18:02:01 UTC` (the jobs' notes' format), empty when absent."""
    return "" if seconds is None else utc_text(seconds)


def not_found_page(what: str) -> str:
    """The page of a 404: what does not exist, and the way back."""
    return page("Not found", f'<p>{esc(what)} does not exist. <a href="/">All boards</a></p>')
