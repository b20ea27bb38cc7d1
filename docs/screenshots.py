"""The documentation site as a reader sees it: build it, serve it on 127.0.0.1, and take
screenshots of a few pages with headless Chromium (Debian's ``chromium`` package).

    python docs/screenshots.py                 # writes docs/screenshots/*.png
    python docs/screenshots.py --out /tmp/shots --pages index,api

Look at the pictures before a release: no raw markup, no broken images, no walls of numbers,
no command cut at the right edge.
"""

from __future__ import annotations

import argparse
import functools
import http.server
import shutil
import subprocess
import sys
import tempfile
import threading
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: The pages taken by default: the home page, the API, the speed reference and a guide.
PAGES = ("index", "api", "speed", "kornia", "gallery", "pytorch2")


def chromium() -> str:
    """The headless browser's executable."""
    for name in ("chromium", "chromium-browser", "google-chrome"):
        path = shutil.which(name)
        if path:
            return path
    sys.exit("screenshots: no chromium here (Debian: apt-get install chromium)")


def build(site: Path) -> None:
    """The site, built strictly into ``site``."""
    cmd = [
        sys.executable,
        "-m",
        "mkdocs",
        "build",
        "--strict",
        "-q",
        "-f",
        str(ROOT / "mkdocs.yml"),
        "-d",
        str(site),
    ]
    subprocess.run(cmd, check=True, cwd=ROOT)


class _Quiet(http.server.SimpleHTTPRequestHandler):
    """A static file handler that logs no request."""

    def log_message(self, format: str, *args: object) -> None:
        return None


def serve(site: Path) -> tuple[http.server.ThreadingHTTPServer, str]:
    """A server of ``site`` on a free port of 127.0.0.1, running in a thread; and its address."""
    handler = functools.partial(_Quiet, directory=str(site))
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    return server, f"http://127.0.0.1:{server.server_address[1]}"


def shoot(browser: str, url: str, path: Path, size: tuple[int, int] = (1280, 2000)) -> None:
    """A screenshot of ``url``, ``size`` (width, height) pixels, written to ``path``."""
    with tempfile.TemporaryDirectory() as profile:
        cmd = [
            browser, "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars",
            f"--user-data-dir={profile}", f"--window-size={size[0]},{size[1]}",
            f"--screenshot={path}", url,
        ]  # fmt: skip
        subprocess.run(cmd, check=True, capture_output=True, timeout=120)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "screenshots", help="folder for the PNGs")
    parser.add_argument("--pages", default=",".join(PAGES), help="comma-separated page names")
    args = parser.parse_args(argv)
    browser = chromium()
    args.out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        site = Path(tmp) / "site"
        build(site)
        server, address = serve(site)
        try:
            for page in args.pages.split(","):
                url = f"{address}/" if page == "index" else f"{address}/{page}/"
                shoot(browser, url, args.out / f"{page}.png")
                print(f"wrote {args.out / f'{page}.png'} ({url})")
        finally:
            server.shutdown()


if __name__ == "__main__":
    main()
