"""The README's screenshot of Rerun's web viewer on a fetch:moved run (docs/view/rerun_fetch.png), redone with

    python docs/view/screenshot.py [--rrd FILE.rrd] [--out docs/view/rerun_fetch.png] [--wait 60]

Without ``--rrd`` it first records a short run (``khgrl up --task fetch:moved --episodes 3 --human-episodes 2
--view rerun:RUN_DIR/fetch.rrd``, a temporary directory). Then it serves the recording with Rerun's CLI (``rerun FILE
--serve-web``), opens the web viewer in headless Chromium (Debian: ``apt-get install chromium``) with software WebGL
(SwiftShader), waits until the viewer has loaded and drawn the data, and saves the page through the DevTools
protocol (a minimal WebSocket client below: no package beyond the standard library and Pillow, which rerun-sdk
installs). Needs rerun-sdk (``pip install 'khgrl[view]'``) and Chromium; no display.
"""

from __future__ import annotations

import argparse
import base64
import io
import json
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
CHROMIUM_FLAGS = ["--headless=new", "--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
                  "--ignore-gpu-blocklist", "--disable-dev-shm-usage", "--hide-scrollbars",
                  "--no-first-run", "--no-default-browser-check"]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_http(url: str, timeout: float) -> bytes:
    deadline = time.monotonic() + timeout
    while True:
        try:
            with urllib.request.urlopen(url, timeout=2) as r:
                return r.read()
        except OSError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.2)


class DevTools:
    """A minimal client of Chromium's DevTools protocol over one WebSocket (RFC 6455 text frames)."""

    def __init__(self, ws_url: str) -> None:
        rest = ws_url.split("://", 1)[1]
        hostport, path = rest.split("/", 1)
        host, port = hostport.split(":")
        self.sock = socket.create_connection((host, int(port)), timeout=120)
        key = base64.b64encode(os.urandom(16)).decode()
        self.sock.sendall((f"GET /{path} HTTP/1.1\r\nHost: {hostport}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
                           f"Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n\r\n").encode())
        head = b""
        while b"\r\n\r\n" not in head:
            head += self.sock.recv(1)
        if b" 101 " not in head.split(b"\r\n", 1)[0]:
            raise ConnectionError(f"no WebSocket: {head[:200]!r}")
        self.next_id = 0

    def _read(self, n: int) -> bytes:
        buf = b""
        while len(buf) < n:
            chunk = self.sock.recv(n - len(buf))
            if not chunk:
                raise ConnectionError("DevTools connection closed")
            buf += chunk
        return buf

    def _frame(self) -> tuple[int, bool, bytes]:
        b0, b1 = self._read(2)
        n = b1 & 0x7F
        if n == 126:
            n = int.from_bytes(self._read(2), "big")
        elif n == 127:
            n = int.from_bytes(self._read(8), "big")
        return b0 & 0x0F, bool(b0 & 0x80), self._read(n)

    def _message(self) -> dict:
        data, fin = b"", False
        while not fin:
            opcode, fin, payload = self._frame()
            if opcode == 9:  # ping
                continue
            data += payload
        return json.loads(data)

    def call(self, method: str, **params) -> dict:
        self.next_id += 1
        data = json.dumps({"id": self.next_id, "method": method, "params": params}).encode()
        mask = os.urandom(4)
        n = len(data)
        head = bytes([0x81]) + (bytes([0x80 | n]) if n < 126 else bytes([0x80 | 126]) + n.to_bytes(2, "big")
                                if n < 65536 else bytes([0x80 | 127]) + n.to_bytes(8, "big"))
        self.sock.sendall(head + mask + bytes(b ^ mask[i % 4] for i, b in enumerate(data)))
        while True:
            msg = self._message()
            if msg.get("id") == self.next_id:
                if "error" in msg:
                    raise RuntimeError(f"{method}: {msg['error']}")
                return msg.get("result", {})



def record(tmp: Path) -> Path:
    """A short fetch:moved run recorded with --view (the human in episode 2)."""
    rrd = tmp / "run" / "fetch.rrd"
    subprocess.run([sys.executable, "-m", "khgrl.deploy.cli", "up", "--task", "fetch:moved", "--episodes", "3",
                    "--human-episodes", "2", "--learning-starts", "64", "--run-dir", str(tmp / "run"),
                    "--no-progress", "--view", f"rerun:{rrd}"], cwd=ROOT, check=True)
    return rrd


def screenshot(rrd: Path, out: Path, wait: float, size: tuple[int, int]) -> None:
    import rerun_cli
    from PIL import Image

    chromium = shutil.which("chromium") or shutil.which("chromium-browser") or shutil.which("google-chrome")
    if chromium is None:
        raise SystemExit("no Chromium: apt-get install chromium")
    grpc, web, devtools = free_port(), free_port(), free_port()
    rerun = Path(rerun_cli.__file__).parent / "rerun"
    server = subprocess.Popen([str(rerun), str(rrd), "--serve-web", "--bind", "127.0.0.1", "--port", str(grpc),
                               "--web-viewer-port", str(web)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    browser = None
    try:
        wait_http(f"http://127.0.0.1:{web}/", 30)
        browser = subprocess.Popen([chromium, *CHROMIUM_FLAGS, f"--remote-debugging-port={devtools}",
                                    f"--window-size={size[0]},{size[1]}", "about:blank"],
                                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        pages = json.loads(wait_http(f"http://127.0.0.1:{devtools}/json/list", 30))
        page = next(p for p in pages if p.get("type") == "page")
        cdp = DevTools(page["webSocketDebuggerUrl"])
        cdp.call("Emulation.setDeviceMetricsOverride", width=size[0], height=size[1], deviceScaleFactor=1,
                 mobile=False)
        # WebGL (SwiftShader): the viewer's WebGPU path asks software WebGPU for a buffer larger than it allows
        # The time cursor stays at the end of the run: neither a #when= fragment on this URL nor synthetic clicks or
        # arrow keys moved it in Rerun 0.41's web viewer (tried); the end of the run shows the last episode's band
        url = f"http://127.0.0.1:{web}/?url=rerun%2Bhttp%3A%2F%2F127.0.0.1%3A{grpc}%2Fproxy&renderer=webgl"
        cdp.call("Page.navigate", url=url)
        time.sleep(wait)  # the viewer's wasm, then the recording over gRPC, then drawing with software WebGL
        png = base64.b64decode(cdp.call("Page.captureScreenshot", format="png")["data"])
    finally:
        for proc in (browser, server):
            if proc is not None:
                proc.terminate()
                proc.wait(10)
    img = Image.open(io.BytesIO(png)).convert("RGB")
    img = img.quantize(colors=128, method=Image.Quantize.MEDIANCUT)  # a small PNG
    out.parent.mkdir(parents=True, exist_ok=True)
    img.save(out, optimize=True)
    print(f"wrote {out} ({out.stat().st_size // 1024} KB, {img.width} x {img.height})")


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--rrd", default=None, help="the recording to show (default: record a fetch:moved run first)")
    p.add_argument("--out", default=str(ROOT / "docs" / "view" / "rerun_fetch.png"),
                   help="the PNG to write (default: docs/view/rerun_fetch.png)")
    p.add_argument("--wait", type=float, default=60.0, help="seconds to wait for the viewer (default: %(default)s)")
    p.add_argument("--size", type=int, nargs=2, default=(1400, 850), metavar=("W", "H"),
                   help="the page size in pixels (default: 1400 850)")
    args = p.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        rrd = Path(args.rrd) if args.rrd else record(Path(tmp))
        screenshot(rrd, Path(args.out), args.wait, tuple(args.size))
    return 0


if __name__ == "__main__":
    sys.exit(main())
