"""The viewer page in a headless browser: pose it (time, morph targets, display) and take
pictures; ``screenshot_glb`` is ``canrig view --screenshot``."""

import dataclasses
import json
import os
from collections.abc import Mapping
from pathlib import Path

from .._io import atomic_path
from ._browser import HeadlessChromium
from ._server import ViewerServer

_TWO_FRAMES = "new Promise((r) => requestAnimationFrame(() => requestAnimationFrame(r)))"


class ViewerPage:
    """The viewer page of ``url`` open in ``browser``, loaded: ``info`` is what the page read
    from the glb (meshes, vertices, morphs, duration, colors, animation)."""

    def __init__(self, browser: HeadlessChromium, url: str):
        self.browser = browser
        browser.navigate(url)
        self.info = browser.evaluate("window.canrig.ready")
        browser.evaluate("window.canrig.pause()")

    def set_time(self, seconds: float) -> float:
        """Show the take at ``seconds`` (clamped to the animation); the time shown."""
        return self.browser.evaluate(f"window.canrig.setTime({float(seconds)!r})")

    def set_morph(self, name: str, value: float | None) -> None:
        """Hold morph target ``name`` at ``value`` over the animation (None: let go)."""
        shown = "null" if value is None else repr(float(value))
        self.browser.evaluate(f"window.canrig.setMorph({json.dumps(name)}, {shown})")

    def set_wireframe(self, on: bool) -> None:
        self.browser.evaluate(f"window.canrig.setWireframe({json.dumps(bool(on))})")

    def set_colors(self, on: bool) -> None:
        self.browser.evaluate(f"window.canrig.setColors({json.dumps(bool(on))})")

    def frame_morphs(self) -> bool:
        """Point the camera at what the morph targets move (a whole avatar's face); False
        when nothing moves (the view is left as it was)."""
        return bool(self.browser.evaluate("window.canrig.frameMorphs()"))

    def screenshot(self) -> bytes:
        """The page as PNG bytes, after the pose set has been drawn."""
        self.browser.evaluate(_TWO_FRAMES)
        return self.browser.screenshot()


@dataclasses.dataclass(frozen=True)
class Screenshot:
    """What ``screenshot_glb`` wrote (its docstring lists the fields)."""

    path: Path
    time: float
    info: dict
    console: tuple[tuple[str, str], ...]
    """The page's console messages ``(level, text)``."""

    @property
    def errors(self) -> list[str]:
        return [text for level, text in self.console if level == "error"]


def screenshot_glb(
    glb: str | os.PathLike,
    out: str | os.PathLike,
    *,
    time: float = 0.0,
    morphs: Mapping[str, float] | None = None,
    wireframe: bool = False,
    colors: bool = True,
    face: bool = False,
    size: tuple[int, int] = (960, 720),
    executable: str | None = None,
) -> Screenshot:
    """Render the viewer page for ``glb`` at ``time`` seconds in headless Chromium and write
    the picture to ``out`` (PNG, atomically).

    ``morphs`` holds targets at fixed weights over the animation; ``colors`` shows COLOR_0
    when the file has it; ``face`` frames the camera on the vertices the morph targets move
    (a whole avatar's face) instead of the whole model. Raises ValueError naming the file
    (``inspect_glb``) or ``morphs`` (an unknown target name), and a RuntimeError
    (``BrowserError``) when Chromium is missing or fails.

    Returns:
        A ``Screenshot``: the ``path`` written, the animation ``time`` shown (s), the page's
        report ``info`` (a dict) and its ``console`` messages ``(level, text)``; ``errors``
        lists the console's error texts.
    """
    out = Path(out)
    if out.suffix.lower() != ".png":
        raise ValueError(f"--screenshot {out}: expected a .png file name")
    if not out.parent.is_dir():
        raise ValueError(f"--screenshot {out}: the folder {out.parent} does not exist")
    with ViewerServer(glb) as server:
        unknown = sorted(set(morphs or {}) - set(server.summary.morph_names))
        if unknown:
            raise ValueError(f"morphs: {glb} has no morph target named {', '.join(unknown)}")
        with HeadlessChromium(executable, width=size[0], height=size[1]) as browser:
            page = ViewerPage(browser, server.url)
            page.set_wireframe(wireframe)
            page.set_colors(colors)
            if face:
                page.frame_morphs()
            for name, value in (morphs or {}).items():
                page.set_morph(name, value)
            shown = page.set_time(time)
            png = page.screenshot()
            console = tuple(browser.console)
    with atomic_path(out) as tmp:
        tmp.write_bytes(png)
    return Screenshot(out, shown, page.info, console)
