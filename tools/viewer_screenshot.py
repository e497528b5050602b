"""Screenshot of Rerun's web viewer on a recording, for docs/figures/viewer.png (docs/viewer.md says how).

Serves RRD with `rerun --web-viewer` on the loopback address, opens it in Debian's headless Chromium (software
WebGL), driven over its DevTools pipe (stdlib only: JSON messages ending in NUL on fds 3 and 4), waits until the
viewer's WASM has loaded and drawn, and writes a PNG. A fixed --virtual-time-budget fired before the WASM loaded.

    .venv/bin/python tools/viewer_screenshot.py runs/demo.rrd docs/figures/viewer.png --wait 240
"""

from __future__ import annotations

import argparse
import base64
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

CHROMIUM = "/usr/bin/chromium-headless-shell"


def _onto_3_and_4(read_end: int, write_end: int) -> None:
    """In the child: Chromium's DevTools pipe reads fd 3 and writes fd 4 (copies first: either may be 3 or 4)."""
    read_copy, write_copy = os.dup(read_end), os.dup(write_end)
    os.dup2(read_copy, 3)
    os.dup2(write_copy, 4)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("rrd", type=Path)
    ap.add_argument("png", type=Path)
    ap.add_argument("--wait", type=float, default=40.0, help="seconds from page load to the screenshot")
    ap.add_argument("--size", default="1600,1000", help="window width,height in pixels")
    ap.add_argument(
        "--do", action="append", default=[], metavar="ACTION", help="after the wait: click:X,Y or wheel:X,Y,DY"
    )
    args = ap.parse_args()
    rerun = Path(sys.executable).with_name("rerun")
    server = subprocess.Popen(
        [rerun, str(args.rrd), "--web-viewer", "--bind", "127.0.0.1", "--web-viewer-port", "9090", "--port", "9876"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,  # the `rerun` script starts the viewer binary: both end with the group
    )
    to_chrome_r, to_chrome_w = os.pipe()
    from_chrome_r, from_chrome_w = os.pipe()
    width, height = args.size.split(",")
    chrome = subprocess.Popen(
        [CHROMIUM, "--no-sandbox", "--remote-debugging-pipe", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
         "--ignore-gpu-blocklist", f"--window-size={width},{height}", "about:blank"],
        start_new_session=True,  # /usr/bin/chromium-headless-shell is a script that starts the browser
        pass_fds=(3, 4),  # kept open after preexec_fn has put the pipe's ends there
        preexec_fn=lambda: _onto_3_and_4(to_chrome_r, from_chrome_w),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )  # fmt: skip
    os.close(to_chrome_r)
    os.close(from_chrome_w)
    reader = os.fdopen(from_chrome_r, "rb")
    ids = iter(range(1, 1_000_000))

    def call(method: str, session: str | None = None, **params) -> dict:
        message_id = next(ids)
        message = {"id": message_id, "method": method, "params": params, **({"sessionId": session} if session else {})}
        os.write(to_chrome_w, json.dumps(message).encode() + b"\0")
        buffer = b""
        while True:
            byte = reader.read(1)
            if not byte:
                raise RuntimeError("chromium closed its DevTools pipe")
            if byte != b"\0":
                buffer += byte
                continue
            reply, buffer = json.loads(buffer), b""
            if reply.get("id") == message_id:
                if "error" in reply:
                    raise RuntimeError(f"{method}: {reply['error']}")
                return reply["result"]

    try:
        time.sleep(3)  # the viewer's HTTP and gRPC servers
        url = "http://127.0.0.1:9090/?url=rerun%2Bhttp://127.0.0.1:9876/proxy"
        target = call("Target.createTarget", url="about:blank")["targetId"]
        session = call("Target.attachToTarget", targetId=target, flatten=True)["sessionId"]
        call("Emulation.setDeviceMetricsOverride", session, width=int(width), height=int(height), deviceScaleFactor=1,
             mobile=False)  # fmt: skip
        call("Page.navigate", session, url=url)
        time.sleep(args.wait)
        for action in args.do:  # the timeline, a panel's maximize button, the panels' toggles, zoom
            kind, _, numbers = action.partition(":")
            x, y, *dy = (float(v) for v in numbers.split(","))
            call("Input.dispatchMouseEvent", session, type="mouseMoved", x=x, y=y)  # egui acts where the pointer is
            if kind == "wheel":
                call("Input.dispatchMouseEvent", session, type="mouseWheel", x=x, y=y, deltaX=0, deltaY=dy[0])
            for event in ("mousePressed", "mouseReleased") if kind == "click" else ():
                call("Input.dispatchMouseEvent", session, type=event, x=x, y=y, button="left", clickCount=1)
            time.sleep(3)
        shot = call("Page.captureScreenshot", session, format="png")
        args.png.write_bytes(base64.b64decode(shot["data"]))
        print(f"wrote {args.png} from {url}")
    finally:
        for process in (chrome, server):
            os.killpg(process.pid, signal.SIGTERM)
        chrome.wait(10)
        server.wait(10)


if __name__ == "__main__":
    main()
