"""The viewer (``jaxplush view``, :func:`jaxplush.io.view`): its command line without the extra, bad
input, subsampling, FIT.h5 and targets, and the live server and the static HTML in a real headless
browser.

The browser tests drive a system Chromium (Debian's ``chromium-headless-shell``, which .ci/run
installs) through playwright's ``executable_path`` with software WebGL (SwiftShader); they skip,
saying why, when viser, playwright or the browser is missing. Each keeps its last screenshot under
its ``tmp_path``.
"""

from __future__ import annotations

import importlib.util
import os
import shutil
import signal
import subprocess
import sys
import time
import urllib.parse

import h5py
import numpy as np
import pytest

from jaxplush import cli

VIEW = sys.modules["jaxplush.io.view"]        # the module (jaxplush.io.view is the function)
HAVE_VISER = importlib.util.find_spec("viser") is not None
needs_viser = pytest.mark.skipif(not HAVE_VISER, reason='viser not installed (pip install -e ".[viewer]")')
#: Where Debian's chromium-headless-shell puts the browser (the real binary first; /usr/bin holds a wrapper).
BROWSERS = ("/usr/lib/chromium/chromium-headless-shell", "/usr/bin/chromium-headless-shell")
#: Software WebGL: headless Chromium refuses SwiftShader without this.
BROWSER_ARGS = ["--enable-unsafe-swiftshader", "--use-angle=swiftshader"]
VIEWPORT = {"width": 720, "height": 480}
N_FRAMES = 41


def _browser_path():
    env = os.environ.get("JAXPLUSH_BROWSER")
    return next((p for p in ((env,) if env else BROWSERS) if os.access(p, os.X_OK)), None)


def _icosphere(radius, centre):
    import trimesh
    m = trimesh.creation.icosphere(subdivisions=2, radius=radius)
    return np.asarray(m.vertices) + centre, np.asarray(m.faces)


@pytest.fixture(scope="module")
def traj(tmp_path_factory):
    """A trajectory file: two balls (two objects) falling from 0.5 m to the floor at y = 0 and squashing."""
    d = tmp_path_factory.mktemp("view")
    (va, fa), (vb, fb) = _icosphere(0.1, (-0.2, 0.5, 0)), _icosphere(0.08, (0.2, 0.5, 0))
    rest = np.concatenate([va, vb])
    faces = np.concatenate([fa, fb + len(va)]).astype(np.int32)
    oid = np.repeat([0, 1], [len(va), len(vb)]).astype(np.int32)
    times = np.linspace(0, 0.4, N_FRAMES)
    pos = np.empty((N_FRAMES, len(rest), 3), np.float32)
    for k, s in enumerate(times / times[-1]):
        x = rest.copy()
        x[:, 1] -= 0.38 * s                                     # fall
        c = x[oid == 0].mean(axis=0)
        x[oid == 0] = c + (x[oid == 0] - c) * (1 + 0.2 * s, 1 - 0.2 * s, 1 + 0.2 * s)   # squash: strain
        pos[k] = x
    path = d / "two.h5"
    with h5py.File(path, "w") as f:
        f["positions"], f["times"], f["faces"], f["object_id"] = pos, times, faces, oid
        f.create_dataset("object_names", data=np.array(["left", "right"], dtype=object),
                         dtype=h5py.string_dtype("utf-8"))
        f.attrs["floor"] = 0.0
        f.attrs["dt"], f.attrs["save_every"] = 0.001, 10
    return path


def _run(argv, capsys):
    rc = cli.main(argv)
    out = capsys.readouterr()
    return rc, out.out, out.err


# ----------------------------------------------------------------------------
# the command line: no extra, bad input, subsampling (no browser)
# ----------------------------------------------------------------------------


@pytest.mark.parametrize("extra", [[], ["--html", "out.html"]])
def test_without_viser_prints_the_install_hint_and_exits_2(traj, tmp_path, capsys, monkeypatch, extra):
    monkeypatch.setitem(sys.modules, "viser", None)           # import viser -> ImportError
    monkeypatch.chdir(tmp_path)
    rc, out, err = _run(["view", str(traj)] + extra, capsys)
    assert rc == 2 and "Traceback" not in err
    assert err.startswith("jaxplush view: error: the viewer needs the optional package viser")
    assert 'pip install -e ".[viewer]"' in err and 'pip install "jaxplush[viewer]"' in err
    assert os.listdir(tmp_path) == []


def test_without_viser_in_a_fresh_interpreter(traj, tmp_path):
    """The import blocker in a subprocess: nothing imported viser before."""
    code = ("import sys; sys.modules['viser'] = None\n"
            "from jaxplush.cli import main\n"
            f"sys.exit(main(['view', {str(traj)!r}]))")
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert p.returncode == 2 and "Traceback" not in p.stderr and 'pip install -e ".[viewer]"' in p.stderr


def _bad_files(d, traj):
    text = d / "scene.h5"
    text.write_text("o ball\n")
    empty = d / "empty.h5"
    with h5py.File(empty, "w") as f:
        f["something"] = np.zeros(3)
    running = d / "running.h5"
    with h5py.File(running, "w") as f:
        f.attrs["status"] = "running"
        f.create_group("checkpoint")
    nan = d / "nan.h5"
    shutil.copy(traj, nan)
    with h5py.File(nan, "a") as f:
        f["positions"][5, 3] = np.nan
    return {"missing": (d / "nope.h5", "no such file"), "not HDF5": (text, "not an HDF5 file"),
            "no positions": (empty, "missing dataset 'positions'"),
            "unfinished fit": (running, "without a fitted rollout"),
            "non-finite": (nan, "non-finite values (first at frame 5")}


@pytest.mark.parametrize("case", ["missing", "not HDF5", "no positions", "unfinished fit", "non-finite",
                                  "bad target", "bad option"])
def test_bad_input_names_the_file_and_exits_2(traj, tmp_path, capsys, monkeypatch, case):
    monkeypatch.setattr(VIEW, "require_viser", lambda: None)     # the input is read before viser is used
    bad = _bad_files(tmp_path, traj)
    out_html = tmp_path / "out.html"
    if case == "bad target":
        argv, name, message = ["view", str(traj), "--target", str(bad["not HDF5"][0])], bad["not HDF5"][0], \
            "not an HDF5 file"
    elif case == "bad option":
        argv, name, message = ["view", str(traj), "--html", str(tmp_path / "out.txt")], tmp_path / "out.txt", \
            "must end in .html or .htm"
    else:
        (name, message), argv = bad[case], ["view", str(bad[case][0])]
    rc, out, err = _run(argv + ([] if "--html" in argv else ["--html", str(out_html)]), capsys)
    assert rc == 2, err
    assert err.startswith(f"jaxplush view: error: {name}: ") and message in err and "Traceback" not in err
    assert not out_html.exists() and not [n for n in os.listdir(tmp_path) if n.startswith(".tmp-")]


@needs_viser
def test_html_subsamples_and_says_so(traj, tmp_path, capsys):
    out = tmp_path / "view.html"
    rc, text, err = _run(["view", str(traj), "--max-frames", "7", "--color", "strain", "--html", str(out)], capsys)
    assert rc == 0, err
    assert f"showing 7 of {N_FRAMES} frames (evenly spaced, first and last kept" in text
    assert "strain colours (edge length / rest length)" in text and "rest lengths from frame 0" in text
    assert f"wrote {out}" in text
    doc = out.read_text()
    assert "window.__VISER_EMBED_DATA__=" in doc and doc.rstrip().endswith("</html>")
    # self-contained: no address to fetch (the only URL is the SVG namespace of the inline icon)
    urls = {u for u in _urls(doc) if u != "http://www.w3.org/2000/svg"}
    assert urls == set(), urls
    assert [n for n in os.listdir(tmp_path)] == ["view.html"]             # written atomically, no leftovers
    rc, text, _ = _run(["view", str(traj), "--html", str(out)], capsys)
    assert rc == 0 and "showing" not in text                                 # all frames: nothing to say


def _urls(text):
    import re
    return set(re.findall(r"https?://[A-Za-z0-9.\-]+(?::\d+)?(?:/[^\s\"'<>)]*)?", text))


@needs_viser
def test_fit_file_shows_the_fitted_rollout_against_its_target(traj, tmp_path):
    """A FIT.h5 (jaxplush-fit's layout: the scene text, fitted/positions and fitted/times, the target's
    path): its target is found beside it and drawn at the matching frames."""
    import jaxplush
    with h5py.File(traj) as f:
        pos, times, faces = f["positions"][()], f["times"][()], f["faces"][()]
    verts = pos[0].astype(np.float64)
    lines = ["floor 0.0"]
    with h5py.File(traj) as f:
        oid = f["object_id"][()]
    for o, name in enumerate(("left", "right")):                # OBJ indices are 1-based, global to the file
        lines += [f"o {name}", "k_structural 100", "total_weight 0.1"]
        lines += [f"v {x:.9g} {y:.9g} {z:.9g}" for x, y, z in verts[oid == o]]
        lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in faces[oid[faces[:, 0]] == o]]
    scene_text = "\n".join(lines) + "\n"
    assert jaxplush.parse_scene(scene_text).n_vertices == pos.shape[1]
    target = tmp_path / "target.h5"
    with h5py.File(target, "w") as f:                          # every 4th frame, as points
        f["points"], f["times"] = pos[::4, ::3], times[::4]
    fit = tmp_path / "FIT.h5"
    with h5py.File(fit, "w") as f:
        f.attrs["status"], f.attrs["scene"], f.attrs["scene_path"] = "converged", scene_text, "start.obj"
        f.attrs["target_path"] = "elsewhere/target.h5"             # as recorded: not found; beside FIT.h5: found
        f["fitted/positions"], f["fitted/steps"], f["fitted/times"] = pos, np.arange(N_FRAMES) * 10, times
    lines_out = []
    v = jaxplush.io.view(str(fit), html=True, report=lines_out.append)
    assert v.path is None and "__VISER_EMBED_DATA__" in v.html and "srcdoc=" in v._repr_html_()
    assert lines_out == [f"target {tmp_path / 'target.h5'}: {len(times[::4])} frames of points; shown at "
                         f"{len(times[::4])} of the {N_FRAMES} frames (those at a target frame's time)"]
    lines_out.clear()
    jaxplush.io.view(str(fit), html=True, color="strain", report=lines_out.append, target=str(traj))
    assert "rest lengths from the stored scene" in lines_out[-1] and "frames of positions" in lines_out[0]
    os.remove(target)
    lines_out.clear()
    jaxplush.io.view(str(fit), html=True, report=lines_out.append)
    assert "is not found" in lines_out[0] and "--target names it" in lines_out[0]


# ----------------------------------------------------------------------------
# in a real browser
# ----------------------------------------------------------------------------


@pytest.fixture(scope="module")
def browser():
    if not HAVE_VISER:
        pytest.skip('viser not installed (pip install -e ".[viewer]")')
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        pytest.skip("playwright not installed (pip install playwright; it is in the test extra)")
    path = _browser_path()
    if path is None:
        pytest.skip(f"no headless Chromium at {os.environ.get('JAXPLUSH_BROWSER') or ' or '.join(BROWSERS)} "
                    "(apt-get install chromium-headless-shell, as .ci/run does; or set JAXPLUSH_BROWSER)")
    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=path, args=BROWSER_ARGS)
        yield b
        b.close()


class _Page:
    """A page that records every request, and screenshots as arrays with the overlays blanked."""

    def __init__(self, browser, url):
        self.page = browser.new_page(viewport=VIEWPORT)
        self.requests = []
        self.page.on("request", lambda r: self.requests.append(r.url))
        self.page.goto(url, wait_until="commit")

    def shot(self, path=None):
        """The page as (H, W, 3) int array; the software-WebGL notice, viser's panels and the playback
        bar (text, not the scene) are zeroed."""
        from PIL import Image
        import io
        png = self.page.screenshot()
        if path:
            with open(path, "wb") as fh:
                fh.write(png)
        img = np.asarray(Image.open(io.BytesIO(png)).convert("RGB")).astype(int)
        boxes = self.page.evaluate("""() => [...document.querySelectorAll(
            '.mantine-Notification-root, .mantine-Paper-root, input, [role=slider]')].map(e => {
                const r = e.getBoundingClientRect(); return [r.left, r.top, r.right, r.bottom]; })""")
        for x0, y0, x1, y1 in boxes:
            img[max(int(y0) - 2, 0):int(y1) + 3, max(int(x0) - 2, 0):int(x1) + 3] = 0
        return img

    def rendered(self, timeout=60):
        """Wait until an object is drawn and the picture holds still; return it."""
        end = time.monotonic() + timeout
        last = None
        while time.monotonic() < end:
            img = self.shot()
            if any(c.mean() > 1e-3 for c in _objects(img)) and last is not None and _changed(img, last) < 1e-4:
                return img
            last = img
            time.sleep(0.3)
        raise AssertionError(f"the scene was not drawn within {timeout} s")

    def hosts(self):
        return {urllib.parse.urlsplit(u).scheme + ":" + (urllib.parse.urlsplit(u).hostname or "")
                for u in self.requests}


def _objects(img):
    """Masks of the two objects' colours (blue #4C72B0 and orange #DD8452, shaded)."""
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    return (b > r + 40) & (b > g + 10), (r > b + 60) & (r > g + 20)


def _has_both_objects(img):
    return all(c.mean() > 1e-3 for c in _objects(img))


def _changed(a, b):
    """Fraction of pixels that differ visibly."""
    return float((np.abs(a - b).max(axis=2) > 40).mean())


def test_live_viewer_in_a_browser(browser, traj, tmp_path):
    import jaxplush
    v = jaxplush.io.view(str(traj), max_frames=21, report=None)
    try:
        assert v.url.startswith("http://127.0.0.1:") and f'src="{v.url}"' in v._repr_html_()
        page = _Page(browser, v.url)
        page.page.wait_for_selector("[role=slider]", timeout=60000)
        first = page.rendered()
        assert np.std(first) > 10                                      # not blank
        slider = page.page.locator("[role=slider]").first
        slider.focus()
        page.page.keyboard.press("End")                                # the timeline to the last frame
        deadline = time.monotonic() + 10
        while v.slider.value != 20 and time.monotonic() < deadline:
            time.sleep(0.1)
        assert v.slider.value == 20
        page.page.get_by_role("button", name="Play").click()          # plays on from the start
        deadline = time.monotonic() + 10
        while v.slider.value in (0, 20) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert 0 < v.slider.value < 20 and v.button.label == "Pause"
        page.page.get_by_role("button", name="Pause").click()
        deadline = time.monotonic() + 10
        while v.button.label != "Play" and time.monotonic() < deadline:
            time.sleep(0.05)
        held = v.slider.value
        time.sleep(0.3)
        assert v.slider.value == held                                  # paused
        slider.focus()
        page.page.keyboard.press("End")
        deadline = time.monotonic() + 10
        while v.slider.value != 20 and time.monotonic() < deadline:
            time.sleep(0.1)
        last = page.rendered()
        assert _changed(first, last) > 2e-3, "moving the timeline did not change the picture"
        assert _has_both_objects(last)             # each in its colour (landed: below viser's control panel)
        page.shot(tmp_path / "live.png")
        assert page.hosts() <= {"http:127.0.0.1", "ws:127.0.0.1", "blob:", "data:"}, page.requests
        page.page.close()
    finally:
        v.stop()


def test_static_html_in_a_browser(browser, traj, tmp_path):
    import jaxplush
    out = tmp_path / "view.html"
    jaxplush.io.view(str(traj), html=out, report=None)
    page = _Page(browser, out.as_uri())
    page.page.wait_for_selector("input", timeout=60000)               # the player's time field
    time_field = page.page.locator("input").first

    def at(t):                                                          # jump there (the player pauses)
        time_field.fill(str(t))
        time_field.press("Tab")
        return page.rendered()

    start = at(0.01)
    assert np.std(start) > 10 and _has_both_objects(start)
    end = at(0.39)
    assert _changed(start, end) > 2e-3, "moving the timeline did not change the picture"
    page.shot(tmp_path / "static.png")
    assert page.hosts() <= {"file:", "blob:", "data:"}, page.requests
    page.page.close()


def test_ctrl_c_stops_the_server_with_130(traj):
    if not HAVE_VISER:
        pytest.skip('viser not installed (pip install -e ".[viewer]")')
    # as from a terminal: a run started in the background of a non-interactive shell (nohup ... &, as
    # CI may be) inherits SIGINT ignored, and Python then installs no KeyboardInterrupt handler
    p = subprocess.Popen([sys.executable, "-m", "jaxplush", "view", str(traj)], stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True,
                         preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        line = p.stdout.readline()
        assert line.startswith(f"viewing {traj} at http://127.0.0.1:") and "(Ctrl-C stops)" in line, line
        import urllib.request
        url = line.split(" at ")[1].split()[0]
        assert b"<html" in urllib.request.urlopen(url, timeout=10).read(2000)
        p.send_signal(signal.SIGINT)
        out, err = p.communicate(timeout=30)
    finally:
        if p.poll() is None:
            p.kill()
    assert p.returncode == 130 and err == "jaxplush view: stopped\n"
