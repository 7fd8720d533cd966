"""Screenshot each built-in world's recording in rerun's web viewer, as a user first sees it.

    python sims/screenshots.py [--worlds beacons,quadrotor-uwb,plaza1] [--out docs/figures]
                               [--duration S] [--wait S] [--size 1600x1000] [--scale 0.75]

For each world the script records a short run with the command-line tool (``quadobs run``
for a simulated scenario, ``quadobs replay`` for a log), serves the ``.rrd`` with
``rerun FILE --web-viewer`` bound to 127.0.0.1 only, opens the viewer in headless Chromium
and writes ``viewer-WORLD.png``. The viewer draws with WebGL: Chromium renders it in
software (SwiftShader through ANGLE), so no GPU is needed. Chromium's own ``--screenshot``
fires before the viewer's WebAssembly has loaded, so the script drives Chromium through
the DevTools protocol over a pipe (``--remote-debugging-pipe``: no port opened) and takes
the screenshot once the page has stopped changing. The viewer and Chromium are stopped on
every exit path, within a few seconds.

Needs ``chromium`` on the PATH (Debian: ``apt-get install chromium``); ``plaza1`` needs the
log's download to be possible or already cached.
"""

import argparse
import base64
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from urllib.parse import quote

from quadobs.errors import run_script

#: world -> command-line arguments of quadobs that record it (a replay needs no duration)
WORLDS = {
    "beacons": ["run", "beacons"],
    "quadrotor-uwb": ["run", "quadrotor-uwb"],
    "plaza1": ["replay", "plaza1"],
}


def find_chromium() -> str | None:
    """Chromium's executable on the PATH, or None."""
    return shutil.which("chromium") or shutil.which("chromium-browser")


def free_port() -> int:
    """A TCP port free on 127.0.0.1 now (the OS picks it)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def record(world: str, duration: float, rrd: Path) -> None:
    """Record a short run of ``world`` to ``rrd`` with the command-line tool."""
    args = [*WORLDS[world], "--out", str(rrd), "--no-progress"]
    if args[0] == "run":
        args += ["--duration", f"{duration:g}"]
    done = subprocess.run(
        [sys.executable, "-m", "quadobs.cli", "-q", *args],
        capture_output=True,
        text=True,
        timeout=600,
    )
    if done.returncode != 0 or not rrd.is_file():
        raise RuntimeError(f"recording {world} failed: {done.stderr.strip()[-500:]}")


def stop(proc: subprocess.Popen) -> None:
    """Stop a process group started by this script: SIGTERM, then SIGKILL after 5 s."""
    if proc.poll() is not None:
        return
    try:
        os.killpg(proc.pid, signal.SIGTERM)
        proc.wait(timeout=5)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(timeout=5)
    except ProcessLookupError:
        pass


def serve(rrd: Path, log) -> tuple[subprocess.Popen, str]:
    """Start ``rerun FILE --web-viewer`` on 127.0.0.1; return it and the viewer's address."""
    web, grpc = free_port(), free_port()
    rerun = shutil.which("rerun", path=str(Path(sys.executable).parent)) or "rerun"
    proc = subprocess.Popen(
        [rerun, str(rrd), "--web-viewer", "--bind", "127.0.0.1"]
        + ["--web-viewer-port", str(web), "--port", str(grpc), "--hide-welcome-screen"],
        stdout=log,
        stderr=subprocess.STDOUT,
        start_new_session=True,
    )
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f"rerun exited with status {proc.returncode}")
        try:
            socket.create_connection(("127.0.0.1", web), timeout=1).close()
            break
        except OSError:
            time.sleep(0.2)
    else:
        stop(proc)
        raise RuntimeError("rerun's web viewer did not start listening within 30 s")
    source = quote(f"rerun+http://127.0.0.1:{grpc}/proxy", safe="")
    return proc, f"http://127.0.0.1:{web}/?url={source}"


class DevTools:
    """Headless Chromium driven by the DevTools protocol over a pipe (JSON messages, NUL-ended)."""

    def __init__(self, width: int, height: int, log) -> None:
        chromium = find_chromium()
        if chromium is None:
            raise RuntimeError("chromium is not on the PATH")
        self.commands_r, self.commands_w = os.pipe()  # we write, Chromium reads (its fd 3)
        self.replies_r, self.replies_w = os.pipe()  # Chromium writes (its fd 4), we read
        self.profile = tempfile.mkdtemp(prefix="quadobs-chromium-")
        flags = [
            "--headless",
            "--no-sandbox",
            "--remote-debugging-pipe",
            "--use-angle=swiftshader",  # WebGL in software, no GPU needed
            "--enable-unsafe-swiftshader",
            "--ignore-gpu-blocklist",
            "--hide-scrollbars",
            "--no-first-run",
            f"--user-data-dir={self.profile}",
            f"--window-size={width},{height}",
            "about:blank",
        ]
        self.proc = subprocess.Popen(
            [chromium, *flags],
            stdin=subprocess.DEVNULL,
            stdout=log,
            stderr=log,
            pass_fds=(3, 4),
            preexec_fn=self._pipes_as_3_and_4,
            start_new_session=True,
        )
        os.close(self.commands_r)
        os.close(self.replies_w)
        self.next_id, self.buffer, self.session = 0, b"", None
        self.width, self.height = width, height

    def _pipes_as_3_and_4(self) -> None:
        os.dup2(self.commands_r, 3)
        os.dup2(self.replies_w, 4)

    def call(self, method: str, timeout: float = 30.0, **params) -> dict:
        """Send one command (to the attached page, once attached) and return its result."""
        self.next_id += 1
        message = {"id": self.next_id, "method": method, "params": params}
        if self.session is not None:
            message["sessionId"] = self.session
        os.write(self.commands_w, json.dumps(message).encode() + b"\0")
        deadline = time.monotonic() + timeout
        while True:
            while b"\0" in self.buffer:
                raw, self.buffer = self.buffer.split(b"\0", 1)
                reply = json.loads(raw)
                if reply.get("id") == self.next_id:
                    if "error" in reply:
                        raise RuntimeError(f"{method}: {reply['error']}")
                    return reply["result"]
            if time.monotonic() > deadline or self.proc.poll() is not None:
                raise RuntimeError(f"chromium did not answer {method}")
            os.set_blocking(self.replies_r, False)
            try:
                chunk = os.read(self.replies_r, 1 << 20)
            except BlockingIOError:
                time.sleep(0.05)
                continue
            if not chunk:
                raise RuntimeError("chromium closed its DevTools pipe")
            self.buffer += chunk

    def open(self, url: str) -> None:
        """Attach to the first page and navigate it to ``url``."""
        pages = [t for t in self.call("Target.getTargets")["targetInfos"] if t["type"] == "page"]
        attached = self.call("Target.attachToTarget", targetId=pages[0]["targetId"], flatten=True)
        self.session = attached["sessionId"]
        self.call("Page.enable")
        self.call(  # the page's viewport, exactly (the window also holds the browser's frame)
            "Emulation.setDeviceMetricsOverride",
            width=self.width,
            height=self.height,
            deviceScaleFactor=1,
            mobile=False,
        )
        self.call("Page.navigate", url=url)

    def screenshot(self, width: int, height: int, scale: float) -> bytes:
        """The page's ``width`` x ``height`` pixels as a PNG, scaled by ``scale``."""
        clip = {"x": 0, "y": 0, "width": width, "height": height, "scale": scale}
        reply = self.call("Page.captureScreenshot", format="png", clip=clip)
        return base64.b64decode(reply["data"])

    def close(self) -> None:
        for fd in (self.commands_w, self.replies_r):
            try:
                os.close(fd)
            except OSError:
                pass
        stop(self.proc)
        shutil.rmtree(self.profile, ignore_errors=True)


def settled_screenshot(browser: DevTools, wait: float, least: float, **clip) -> bytes:
    """Screenshots every 2 s after ``least`` s until two in a row agree, or ``wait`` s pass."""
    start, last = time.monotonic(), b""
    time.sleep(least)
    while True:
        png = browser.screenshot(**clip)
        if png == last or time.monotonic() - start > wait:
            return png
        last = png
        time.sleep(2.0)


def shoot(world: str, args: argparse.Namespace, work: Path) -> Path:
    """Record ``world``, serve it, screenshot the viewer; servers stopped on every path."""
    rrd = work / f"{world}.rrd"
    record(world, args.duration, rrd)
    width, height = (int(v) for v in args.size.split("x"))
    out = Path(args.out) / f"viewer-{world}.png"
    with open(work / f"{world}.log", "w") as log:
        viewer, url = serve(rrd, log)
        browser = None
        try:
            browser = DevTools(width, height, log)
            browser.open(url)
            png = settled_screenshot(
                browser, args.wait, least=8.0, width=width, height=height, scale=args.scale
            )
            out.write_bytes(png)
        finally:
            if browser is not None:
                browser.close()
            stop(viewer)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--worlds", default=",".join(WORLDS), help="comma-separated, of: " + ", ".join(WORLDS)
    )
    parser.add_argument("--out", default="docs/figures", help="folder for viewer-WORLD.png")
    parser.add_argument("--duration", type=float, default=10.0, help="simulated run length (s)")
    parser.add_argument(
        "--wait", type=float, default=60.0, help="most seconds to let the viewer settle"
    )
    parser.add_argument("--size", default="1600x1000", help="window size WIDTHxHEIGHT (pixels)")
    parser.add_argument("--scale", type=float, default=0.75, help="PNG size over window size")
    args = parser.parse_args()
    worlds = args.worlds.split(",")
    unknown = sorted(set(worlds) - set(WORLDS))
    if unknown:
        parser.error(f"unknown world(s) {', '.join(unknown)}; known: {', '.join(WORLDS)}")
    if find_chromium() is None:
        parser.error("chromium is not on the PATH (Debian: apt-get install chromium)")
    Path(args.out).mkdir(parents=True, exist_ok=True)
    # a SIGTERM unwinds like Ctrl-C, so that the viewer and Chromium are stopped on the way out
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))
    with tempfile.TemporaryDirectory(prefix="quadobs-screenshots-") as work:
        for world in worlds:
            try:
                path = shoot(world, args, Path(work))
            except (RuntimeError, OSError, subprocess.SubprocessError) as err:
                sys.exit(f"screenshots: {world}: {err}")
            print(f"{world}: screenshot {path} ({path.stat().st_size} bytes)")


if __name__ == "__main__":
    run_script(main, Path(__file__).name)
