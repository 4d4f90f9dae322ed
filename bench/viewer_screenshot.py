"""The README's picture of the browser viewer: ``dofsplat view --demo`` in headless Chromium,
after a click on the floor has pulled the focus there.

    python bench/viewer_screenshot.py [-o docs/images/viewer.png]

Needs Debian's chromium and Playwright (``pip install -e ".[test]"``).
"""

from __future__ import annotations

import argparse
import shutil
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("-o", "--output", default=str(ROOT / "docs/images/viewer.png"))
    args = ap.parse_args(argv)
    from playwright.sync_api import sync_playwright

    chromium = shutil.which("chromium")
    if chromium is None:
        print("no chromium (apt-get install chromium)", file=sys.stderr)
        return 1
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    proc = subprocess.Popen([sys.executable, "-m", "dofsplat", "view", "--demo", "--port",
                             str(port), "--host", "127.0.0.1", "--no-browser"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    lines = []
    threading.Thread(target=lambda: lines.extend(proc.stderr), daemon=True).start()

    def wait_for(text, after=0):
        while not any(text in line for line in lines[after:]):
            time.sleep(0.1)

    try:
        wait_for("viewer at")
        with sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=chromium, headless=True, args=[
                "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                "--disable-background-networking", "--disable-component-update",
                "--disable-sync"])
            page = browser.new_page(viewport={"width": 1000, "height": 600})
            page.goto(f"http://127.0.0.1:{port}")
            wait_for("sent")
            n = len(lines)
            page.mouse.click(230, 350)  # the near floor, beside the red sphere
            wait_for("focus on the surface", n)
            wait_for("sent", n + 1)
            # headless Chromium draws WebGL in software, and viser says so in a toast that
            # would cover the picture: close it (a GPU-backed browser shows none)
            close = page.locator("button.mantine-Notification-closeButton")
            for i in range(close.count()):
                close.nth(i).click(timeout=2000)
            time.sleep(1.5)
            page.screenshot(path=args.output)
            browser.close()
    finally:
        proc.terminate()
        proc.wait(timeout=20)
    print(f"wrote {args.output}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
