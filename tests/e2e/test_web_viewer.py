"""``codearcade view --serve-web`` in a real browser: headless Chromium renders the recording.

Needs the system Chromium (``apt-get install -y chromium``) and the ``playwright`` package (driving that
Chromium through ``executable_path``; never ``playwright install``); skipped when either is absent. The page is
screenshotted until it stops changing (the web viewer takes ~20-30 s to load on two cores), then the
screenshot must show the game: Pong's brown playfield covers a good part of the 2D view, which the welcome
page (what the viewer shows without data) has none of.
"""

from __future__ import annotations

import io
import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from pipeline.cli import main
from tests.conftest import EXAMPLES, ROOT

CHROMIUM = "/usr/bin/chromium"
CHROMIUM_FLAGS = ["--no-sandbox", "--no-first-run", "--disable-background-networking", "--disable-component-update",
                  "--disable-sync", "--disable-quic"]
PONG_PLAYFIELD = np.array([144, 72, 17])
"""The colour of Pong's playfield in the ALE palette."""

pytestmark = [pytest.mark.skipif(not os.path.exists(CHROMIUM), reason="needs the system Chromium (apt-get install chromium)"),
              pytest.mark.slow]


def _fraction_of(image: np.ndarray, color: np.ndarray, tolerance: int = 12) -> float:
    return float((np.abs(image.astype(int) - color).max(axis=2) <= tolerance).mean())


def _settled_screenshot(page, path: Path, timeout_s: float = 150.0, interval_s: float = 2.0) -> np.ndarray:
    """Screenshots until two in a row are identical; the last one."""
    from PIL import Image

    deadline = time.monotonic() + timeout_s
    previous = None
    while True:
        time.sleep(interval_s)
        png = page.screenshot()
        path.write_bytes(png)
        image = np.asarray(Image.open(io.BytesIO(png)).convert("RGB"))
        if previous is not None and np.array_equal(image, previous):
            return image
        if time.monotonic() > deadline:
            return image
        previous = image


def test_served_web_viewer_shows_the_episode(store, tmp_path, capsys):
    playwright = pytest.importorskip("playwright.sync_api", reason="needs the playwright package")
    code = main(["eval", str(EXAMPLES / "pong.py"), "--trace", "--max-steps", "150", "--store", str(store.path),
                 "--json"])
    out, err = capsys.readouterr()
    assert code == 0, err
    run_id = json.loads(out)["run_id"]

    server = subprocess.Popen([sys.executable, "-m", "pipeline.cli", "view", run_id, "--serve-web", "--store",
                               str(store.path)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT)
    try:
        url = None
        for line in server.stdout:
            match = re.search(r"open (http://\S+)", line)
            if match:
                url = match.group(1)
                break
        assert url is not None, server.stderr.read()
        assert url.startswith("http://127.0.0.1:") and "?url=rerun%2Bhttp%3A%2F%2F127.0.0.1%3A" in url
        assert url.endswith("%2Fproxy")

        with playwright.sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, headless=True, args=CHROMIUM_FLAGS)
            try:
                page = browser.new_page(viewport={"width": 1280, "height": 800})
                page.goto(url, timeout=120_000)
                shot = _settled_screenshot(page, tmp_path / "viewer.png")
            finally:
                browser.close()
        playfield = _fraction_of(shot, PONG_PLAYFIELD)
        assert playfield > 0.05, f"the game frame is not on screen ({playfield:.1%} playfield pixels; {tmp_path}/viewer.png)"
        assert shot.std() > 20, "a blank page"
    finally:
        server.send_signal(signal.SIGINT)
        try:
            server.wait(20)
        except subprocess.TimeoutExpired:
            server.kill()
    assert server.returncode in (0, 130), server.stderr.read()


def test_compare_side_by_side_blueprint_shows_both_episodes(store, tmp_path, capsys):
    """``compare A B --rerun URL`` into a served web viewer: the blueprint opens with the two game views side by
    side, each showing its episode's frame."""
    playwright = pytest.importorskip("playwright.sync_api", reason="needs the playwright package")
    from viewers.rerun_sinks import start_web_viewer

    competent = ROOT / "tests" / "policies" / "pong_competent.py"
    variant = tmp_path / "pong_dead_zone_4.py"
    variant.write_text(competent.read_text().replace("DEAD_ZONE = 3\n", "DEAD_ZONE = 4\n"))
    with start_web_viewer() as viewer:
        code = main(["compare", str(competent), str(variant), "--max-steps", "200", "--rerun", viewer.grpc_url,
                     "--store", str(store.path), "--json"])
        out, err = capsys.readouterr()
        assert code == 0, err
        assert json.loads(out)["episodes"][0]["first_divergent_step"] is not None
        with playwright.sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, headless=True, args=CHROMIUM_FLAGS)
            try:
                page = browser.new_page(viewport={"width": 1280, "height": 800})
                page.goto(viewer.url, timeout=120_000)
                shot = _settled_screenshot(page, tmp_path / "compare.png")
            finally:
                browser.close()
    top = shot[: shot.shape[0] * 2 // 3]  # the two game views fill the upper part of the layout
    left, right = top[:, : top.shape[1] // 2], top[:, top.shape[1] // 2:]
    for name, half in (("left (A)", left), ("right (B)", right)):
        playfield = _fraction_of(half, PONG_PLAYFIELD)
        assert playfield > 0.05, f"no game frame in the {name} half ({playfield:.1%}; {tmp_path}/compare.png)"
