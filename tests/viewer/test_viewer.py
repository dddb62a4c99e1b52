"""``canrig view``: the page in a real browser (headless Chromium, driven through the DevTools
protocol), the server's boundaries (127.0.0.1 only, no ``../``, clean stop) and bad input.

The take is the linear ICT face rig decimated to about 1,500 vertices (``mesh.decimate``,
``rig.remesh_rig``: a light file, a wireframe that does not fill the face) driven by the real
Live Link Face capture with ``canrig animate``, without head rotation, so that what moves
between two frames is the face. Browser tests skip
with the install command when no Chromium is found (``.ci/run`` installs
``chromium-headless-shell`` from the system packages).
"""

from __future__ import annotations

import http.client
import io
import json
import os
import signal
import socket
import struct
import threading
import time
import urllib.request

import numpy as np
import pytest
from PIL import Image

from canrig_jax import run_command
from canrig_jax.data import load_livelinkface, write_livelink_csv
from canrig_jax.mesh import decimate
from canrig_jax.rig import (
    export_animated_gltf,
    export_gltf,
    find_gltf_validator,
    ict_linear_rig,
    load_gltf_rig,
    remesh_rig,
    validate_gltf,
)
from canrig_jax.viewer import ViewerServer, error_colors, find_chromium, inspect_glb
from canrig_jax.viewer._browser import HeadlessChromium
from canrig_jax.viewer._page import ViewerPage
from canrig_jax.viewer._server import HOST

BACKGROUND = np.array([0x1E, 0x22, 0x26], float)  # the page's clear colour


@pytest.fixture(scope="module")
def take(tmp_path_factory, data_dir):
    """anim.glb: the decimated ICT face rig animated by the Live Link capture (no head
    rotation), with the rig and the capture's jawOpen curve (per key time)."""
    root = tmp_path_factory.mktemp("view")
    face = ict_linear_rig(data_dir)
    coarse = decimate(np.asarray(face.neutral), np.asarray(face.faces), 1500)
    export_gltf(remesh_rig(face, coarse), root / "rig.glb")
    capture = load_livelinkface(data_dir)
    write_livelink_csv(root / "take.csv", capture)
    status = run_command(
        ["animate", str(root / "rig.glb"), str(root / "take.csv"), "-o", str(root / "anim.glb")]
        + ["--no-head-rotation", "--quiet"]
    )
    assert status == 0
    rig = load_gltf_rig(root / "rig.glb")
    frames = np.asarray(capture.frame_number, float)
    times = (frames - frames[0]) / float(capture.fps)
    jaw = np.asarray(capture.weights)[:, list(capture.names).index("JawOpen")]
    return root / "anim.glb", rig, times, jaw


@pytest.fixture(scope="module")
def browser():
    if find_chromium() is None:
        pytest.skip(
            "no headless Chromium: apt-get install chromium-headless-shell (.ci/run does), "
            "or set $CANRIG_CHROMIUM"
        )
    with HeadlessChromium(width=800, height=600) as chromium:
        yield chromium


@pytest.fixture(scope="module")
def page(take, browser):
    with ViewerServer(take[0]) as server:
        yield ViewerPage(browser, server.url)


def _picture(page: ViewerPage) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(page.screenshot())).convert("RGB"), float)


def _region(page: ViewerPage, points: np.ndarray, pad: int = 6) -> tuple[slice, slice]:
    """The pixel box (rows, columns) around ``points`` (rig coordinates) as now drawn."""
    pixels = np.asarray(page.browser.evaluate(f"window.canrig.project({points.tolist()})"))
    (x0, y0), (x1, y1) = pixels.min(axis=0) - pad, pixels.max(axis=0) + pad
    return slice(int(y0), int(y1) + 1), slice(int(x0), int(x1) + 1)


def _mouth_and_still(rig, n_mouth: int = 30, n_still: int = 200):
    """Rest positions of the vertices jawOpen moves most and of those no shape moves."""
    motion = np.linalg.norm(np.asarray(rig.deltas), axis=-1)
    jaw = rig.names.index("jawOpen")
    neutral = np.asarray(rig.neutral)
    return neutral[np.argsort(motion[jaw])[-n_mouth:]], neutral[np.argsort(motion.max(0))[:n_still]]


def test_page_draws_the_face_and_the_take_moves_the_mouth(take, page):
    """Two times of the take, chosen from the capture (jaw closest to closed, most open):
    the head's box is filled with the face; around the mouth the frames differ far more
    than where no blendshape moves the head."""
    _, rig, times, jaw = take
    closed, opened = float(times[np.argmin(jaw)]), float(times[np.argmax(jaw)])
    assert jaw.max() - jaw.min() > 0.5
    assert page.info["meshes"] == 1 and page.info["vertices"] == rig.n_vertices
    assert page.info["animation"] == "take" and abs(page.info["duration"] - times[-1]) < 1e-3
    assert page.info["morphs"][:53] == list(rig.names)

    assert page.set_time(closed) == pytest.approx(closed)
    first = _picture(page)
    x0, y0, x1, y1 = (int(v) for v in page.browser.evaluate("window.canrig.screenBox()"))
    assert 0 <= x0 < x1 <= first.shape[1] and 0 <= y0 < y1 <= first.shape[0]
    drawn = np.abs(first - BACKGROUND).sum(axis=-1) > 12
    inside, outside = drawn[y0:y1, x0:x1].mean(), drawn[y0:y1, : max(x0 - 2, 1)].mean()
    assert inside > 0.25 and outside < 0.01, (inside, outside)

    page.set_time(opened)
    second = _picture(page)
    mouth, still = _mouth_and_still(rig)
    difference = np.abs(second - first)
    around_mouth = difference[_region(page, mouth)].mean()
    where_still = difference[_region(page, still)].mean()
    assert around_mouth > 15 and around_mouth > 3 * where_still, (around_mouth, where_still)
    assert page.browser.errors == []


def test_morph_slider_changes_the_picture(take, page):
    """The jawOpen slider moved to 1 (an input event on the page's own slider) opens the
    mouth; reset hands it back to the animation and the picture returns, pixel for pixel."""
    _, rig, times, jaw = take
    page.set_time(float(times[np.argmin(jaw)]))
    before = _picture(page)
    page.browser.evaluate(
        "(() => { const s = document.querySelector('input[data-morph=\"jawOpen\"]');"
        " s.value = 1; s.dispatchEvent(new Event('input')); })()"
    )
    moved = _picture(page)
    mouth, still = _mouth_and_still(rig)
    around_mouth = np.abs(moved - before)[_region(page, mouth)].mean()
    where_still = np.abs(moved - before)[_region(page, still)].mean()
    assert around_mouth > 15 and around_mouth > 3 * where_still, (around_mouth, where_still)
    page.browser.evaluate("document.getElementById('reset').click()")
    np.testing.assert_array_equal(_picture(page), before)
    page.set_wireframe(True)
    wire = _picture(page)
    page.set_wireframe(False)
    x0, y0, x1, y1 = (int(v) for v in page.browser.evaluate("window.canrig.screenBox()"))
    filled = lambda p: (np.abs(p[y0:y1, x0:x1] - BACKGROUND).sum(axis=-1) > 12).mean()  # noqa: E731
    assert 0.05 < filled(wire) < 0.8 * filled(before), (filled(wire), filled(before))
    assert page.browser.errors == []


def test_play_runs_the_take_and_the_slider_scrubs_it(page):
    page.set_time(0.0)
    page.browser.evaluate("document.getElementById('play').click()")
    page.browser.evaluate("new Promise((r) => setTimeout(r, 400))")
    page.browser.evaluate("document.getElementById('play').click()")
    played = page.browser.evaluate("window.canrig.time()")
    assert 0.1 < played < page.info["duration"]  # ran for about 0.4 s, then paused
    assert page.browser.evaluate("document.getElementById('play').textContent") == "play"
    page.browser.evaluate(
        "(() => { const s = document.getElementById('time'); s.value = 2.5;"
        " s.dispatchEvent(new Event('input')); })()"
    )
    assert page.browser.evaluate("window.canrig.time()") == pytest.approx(2.5)
    assert page.browser.evaluate("document.getElementById('clock').textContent") == "2.500 s"
    assert page.browser.errors == []


@pytest.mark.bad_input
def test_vertex_colors_are_shown(take, browser, tmp_path):
    """A glb with COLOR_0 (an error map: red where jawOpen moves, white elsewhere): the page
    paints the mouth red, and the colour toggle turns it back to grey."""
    _, rig, _, _ = take
    motion = np.linalg.norm(np.asarray(rig.deltas)[rig.names.index("jawOpen")], axis=-1)
    colors = error_colors(motion, vmax=float(motion.max()))
    np.testing.assert_allclose(colors[np.argmax(motion)], (1, 0, 0))
    np.testing.assert_allclose(colors[np.argmin(motion)], (1, 1, 1), atol=1e-3)
    for bad, name in ((-motion, "error"), (motion[:, None], "error"), (np.nan * motion, "error")):
        with pytest.raises(ValueError, match=name):
            error_colors(bad, 1.0)
    with pytest.raises(ValueError, match="vmax"):
        error_colors(motion, 0.0)
    weights = np.zeros((1, rig.n_blendshapes), np.float32)
    path = export_animated_gltf(rig, weights, tmp_path / "error.glb", vertex_colors=colors)
    assert inspect_glb(path).has_colors
    np.testing.assert_array_equal(load_gltf_rig(path).neutral, rig.neutral)
    if find_gltf_validator() is not None:
        assert validate_gltf(path)["issues"]["numErrors"] == 0
    with pytest.raises(ValueError, match="vertex_colors"):
        export_animated_gltf(rig, weights, tmp_path / "bad.glb", vertex_colors=colors * 2)
    with ViewerServer(path) as server:
        page = ViewerPage(browser, server.url)
        assert page.info["colors"] is True
        mouth, _ = _mouth_and_still(rig, n_mouth=8)
        shown = _picture(page)[_region(page, mouth, pad=2)].reshape(-1, 3).mean(axis=0)
        page.set_colors(False)
        grey = _picture(page)[_region(page, mouth, pad=2)].reshape(-1, 3).mean(axis=0)
    red = lambda rgb: rgb[0] - (rgb[1] + rgb[2]) / 2  # noqa: E731
    assert red(shown) > 40 and abs(red(grey)) < 10, (shown, grey)
    assert browser.errors == []


def test_screenshot_command(take, tmp_path, capsys):
    if find_chromium() is None:
        pytest.skip("no headless Chromium: apt-get install chromium-headless-shell")
    out = tmp_path / "frame.png"
    status = run_command(
        ["view", str(take[0]), "--screenshot", str(out), "--time", "1.5", "--size", "320x240"]
        + ["--morph", "jawOpen=1", "--quiet"]
    )
    captured = capsys.readouterr()
    assert status == 0, captured.err
    assert "at 1.500 s" in captured.out
    picture = np.asarray(Image.open(out).convert("RGB"), float)
    assert picture.shape == (240, 320, 3)
    assert (np.abs(picture - BACKGROUND).sum(axis=-1) > 12).mean() > 0.05
    status = run_command(
        ["view", str(take[0]), "--screenshot", str(out), "--morph", "noSuchShape=1"]
    )
    assert status == 2 and "noSuchShape" in capsys.readouterr().err


# ------------------------------------------------------------------------- the server alone
def _get(port: int, path: str, host: str = HOST) -> tuple[int, bytes]:
    """A raw GET (the path sent as written, no client-side normalisation)."""
    connection = http.client.HTTPConnection(host, port, timeout=10)
    try:
        connection.request("GET", path)
        response = connection.getresponse()
        return response.status, response.read()
    finally:
        connection.close()


def test_server_on_loopback_only_and_refuses_parent_paths(take):
    with ViewerServer(take[0]) as server:
        host, port = server.address
        assert host == "127.0.0.1"
        status, page = _get(port, "/")
        assert status == 200 and b"viewer.js" in page and b"<title>anim.glb</title>" in page
        assert _get(port, "/model.glb") == (200, take[0].read_bytes())
        assert _get(port, "/three.min.js")[0] == 200
        assert b"MIT License" in _get(port, "/three.LICENSE")[1]
        for path in ("/../_server.py", "/%2e%2e/_server.py", "/x/../../etc/passwd", "/..%2f.."):
            assert _get(port, path)[0] == 403, path
        assert _get(port, "/_server.py")[0] == 404
        with pytest.raises(OSError):  # bound to 127.0.0.1: another loopback address refused
            socket.create_connection(("127.0.0.2", port), timeout=5).close()


def test_server_stops_cleanly(take):
    threads = threading.active_count()
    server = ViewerServer(take[0]).start()
    port = server.address[1]
    assert _get(port, "/")[0] == 200
    server.stop()
    server.stop()  # idempotent
    assert threading.active_count() == threads
    with pytest.raises(OSError):
        socket.create_connection((HOST, port), timeout=5).close()
    ViewerServer(take[0], port=port).stop()  # nothing listens there any more


def _free_port() -> int:
    with socket.socket() as s:
        s.bind((HOST, 0))
        return s.getsockname()[1]


def test_view_command_serves_until_interrupted(take, capsys):
    """``canrig view FILE --port N`` serves the page, and Ctrl-C (SIGINT) stops it: exit 0,
    'stopped', the port free."""
    port = _free_port()
    answers = []

    def visit_then_interrupt():
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            try:
                with urllib.request.urlopen(f"http://{HOST}:{port}/model.glb", timeout=5) as r:
                    answers.append(len(r.read()))
                break
            except OSError:
                time.sleep(0.1)
        os.kill(os.getpid(), signal.SIGINT)

    visitor = threading.Thread(target=visit_then_interrupt)
    visitor.start()
    status = run_command(["view", str(take[0]), "--port", str(port)])
    visitor.join()
    out = capsys.readouterr().out
    assert status == 0 and answers == [take[0].stat().st_size]
    assert f"serving on http://127.0.0.1:{port}/" in out and out.rstrip().endswith("stopped")
    assert f"{take[1].n_vertices} vertices" in out and "animation take" in out
    ViewerServer(take[0], port=port).stop()


# ------------------------------------------------------------------------------- bad input
def _glb(document: dict) -> bytes:
    text = json.dumps(document).encode()
    text += b" " * (-len(text) % 4)
    return (
        struct.pack("<III", 0x46546C67, 2, 20 + len(text))
        + struct.pack("<II", len(text), 0x4E4F534A)
        + text
    )


def test_bad_input_names_the_file_or_port(take, tmp_path, capsys, monkeypatch):
    (tmp_path / "notes.glb").write_text("not a glb at all")
    (tmp_path / "empty.glb").write_bytes(_glb({"asset": {"version": "2.0"}, "nodes": [{}]}))
    (tmp_path / "v1.glb").write_bytes(_glb({"asset": {"version": "1.0"}}).replace(b"\2", b"\1", 1))
    cases = [
        (("view", tmp_path / "notes.glb"), "notes.glb: not a binary glTF"),
        (("view", tmp_path / "empty.glb"), "empty.glb: the .glb holds no mesh"),
        (("view", tmp_path / "v1.glb"), "v1.glb: glTF version 1"),
        (("view", tmp_path / "absent.glb"), "absent.glb: not found"),
        (("view", take[0], "--port", "70000"), "--port 70000"),
    ]
    with socket.socket() as busy:
        busy.bind((HOST, 0))
        busy.listen()
        port = busy.getsockname()[1]
        cases.append((("view", take[0], "--port", port), f"--port {port}: already in use"))
        for argv, message in cases:
            status = run_command([str(a) for a in argv])
            err = capsys.readouterr().err
            assert status == 2 and message in err and "Traceback" not in err, (argv, err)
    with pytest.raises(ValueError, match="empty.glb"):
        ViewerServer(tmp_path / "empty.glb")
    status = run_command(["view", str(take[0]), "--screenshot", str(tmp_path / "no" / "x.png")])
    assert status == 2 and "does not exist" in capsys.readouterr().err
    monkeypatch.setenv("CANRIG_CHROMIUM", str(tmp_path / "no-such-browser"))
    status = run_command(["view", str(take[0]), "--screenshot", str(tmp_path / "x.png")])
    err = capsys.readouterr().err
    assert status == 2 and "no headless Chromium" in err and "chromium-headless-shell" in err
    assert not (tmp_path / "x.png").exists()


@pytest.mark.slow
def test_view_process_stops_on_sigterm(take):
    """The console script in its own process: serves, then SIGTERM stops it (exit 0)."""
    import subprocess
    import sys

    port = _free_port()
    process = subprocess.Popen(
        [sys.executable, "-c", "import sys, canrig_jax; sys.exit(canrig_jax.run_command())"]
        + ["view", str(take[0]), "--port", str(port)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and process.poll() is None:
            try:
                assert _get(port, "/")[0] == 200
                break
            except OSError:
                time.sleep(0.2)
        process.send_signal(signal.SIGTERM)
        out, err = process.communicate(timeout=30)
    finally:
        if process.poll() is None:
            process.kill()
    assert process.returncode == 0, err
    assert out.rstrip().endswith("stopped")
    ViewerServer(take[0], port=port).stop()
