"""The report's page: sections of HTML, its figures as PNG and its clips as MP4, each both
embedded in the page and kept beside it."""

from __future__ import annotations

import base64
import html
import io

from matplotlib.figure import Figure

from ede.analysis.stats import Interval

STYLE = """
body { font-family: system-ui, sans-serif; max-width: 1100px; margin: 2em auto; color: #222; }
table { border-collapse: collapse; margin: 1em 0; font-size: 0.9em; }
th, td { border: 1px solid #ccc; padding: 0.3em 0.6em; text-align: right; }
th:first-child, td:first-child { text-align: left; }
img { max-width: 100%; }
.missing { color: #b00; }
code { font-size: 0.85em; }
"""


def _png(figure: Figure) -> bytes:
    """The figure's PNG."""
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=110)
    return buffer.getvalue()


def interval(interval: Interval) -> str:
    """A bootstrap interval, or "missing" where it has no seeds."""
    if interval.n == 0:
        return '<span class="missing">missing</span>'
    return str(interval)


def steps(found: Interval) -> str:
    """An interval of steps to a threshold, or "missing" where it has no seeds."""
    return interval(found) if found.n == 0 else found.steps()


class Page:
    """Sections of HTML and the PNG and MP4 files beside them."""

    def __init__(self) -> None:
        self.parts: list[str] = []
        self.images: dict[str, bytes] = {}
        self.videos: dict[str, bytes] = {}

    def add(self, text: str) -> None:
        self.parts.append(text)

    def figure(self, name: str, figure: Figure, alt: str) -> None:
        data = _png(figure)
        self.images[name] = data
        encoded = base64.b64encode(data).decode()
        self.add(
            f'<img src="data:image/png;base64,{encoded}" alt="{html.escape(alt)}" id="{name}">'
        )

    def video(self, name: str, data: bytes, alt: str) -> None:
        self.videos[name] = data
        encoded = base64.b64encode(data).decode()
        self.add(
            f'<video controls loop muted autoplay playsinline id="{name}" '
            f'title="{html.escape(alt)}" src="data:video/mp4;base64,{encoded}"></video>'
        )

    def html(self, title: str) -> str:
        return (
            f"<!DOCTYPE html>\n<html><head><meta charset='utf-8'><title>{title}</title>"
            f"<style>{STYLE}</style></head><body>\n" + "\n".join(self.parts) + "\n</body></html>\n"
        )
