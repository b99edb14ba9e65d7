"""Load a page in headless Chromium and report what a person would see.

:func:`load_page` copies the page with a small probe script first in its ``<head>`` (the page
itself has no script), opens it with ``--dump-dom`` and ``--screenshot`` in one headless run, and returns:
the probe's verdict (images decoded, ``naturalWidth > 0``, out of all ``<img>``; uncaught
errors), the console messages Chromium logged (``--enable-logging=stderr``), and the
screenshot path.
"""

from __future__ import annotations

import re
import shutil
import subprocess
import tempfile
from dataclasses import dataclass
from pathlib import Path

PROBE = """<script>
window.__errors = 0;
window.addEventListener('error', function () { window.__errors += 1; }, true);
window.addEventListener('load', function () {
  var imgs = Array.prototype.slice.call(document.images);
  var ok = imgs.filter(function (i) { return i.complete && i.naturalWidth > 0; }).length;
  document.title = 'probe:' + ok + '/' + imgs.length + ':errors=' + window.__errors;
});
</script>"""

_TITLE = re.compile(r"<title>probe:(\d+)/(\d+):errors=(\d+)</title>")


def chromium() -> str | None:
    """Path of a Chromium executable, None when none is installed."""
    for name in ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable"):
        found = shutil.which(name)
        if found:
            return found
    return None


@dataclass(frozen=True)
class PageLoad:
    """What the headless browser saw.

    Attributes
    ----------
    images_ok, images_total : int
        ``<img>`` elements decoded (``naturalWidth > 0``) and in total; -1 when the probe did
        not run.
    errors : int
        Error events caught by the probe (script errors, resources failing to load).
    console : list of str
        Console messages Chromium logged.
    screenshot : pathlib.Path
        PNG of the top of the page.
    """

    images_ok: int
    images_total: int
    errors: int
    console: list[str]
    screenshot: Path


def load_page(
    html: Path,
    screenshot: Path,
    width: int = 1280,
    height: int = 4000,
    timeout_s: float = 60.0,
    fragment: str = "",
) -> PageLoad:
    """Open ``html`` (with ``#fragment`` when given) in headless Chromium (see the module docstring)."""
    exe = chromium()
    if exe is None:
        raise RuntimeError("chromium is not installed")
    text = html.read_text(encoding="utf-8")
    probed = html.with_name(f"_probe_{html.name}")
    # the probe goes first in <head>: its error listener must exist before any script runs or
    # image fails (appended at the end, it missed errors raised earlier, now and then)
    m_head = re.search(r"<head[^>]*>", text, flags=re.IGNORECASE)
    cut = m_head.end() if m_head else 0
    probed.write_text(text[:cut] + PROBE + text[cut:], encoding="utf-8")
    with tempfile.TemporaryDirectory(prefix="iotnav-chromium-") as profile:
        cmd = [
            exe,
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--disable-quic",
            "--no-first-run",
            "--disable-background-networking",
            "--disable-component-update",
            "--disable-sync",
            f"--user-data-dir={profile}",
            "--enable-logging=stderr",
            "--v=0",
            "--hide-scrollbars",
            f"--window-size={width},{height}",
            f"--screenshot={screenshot}",
            "--dump-dom",
            probed.resolve().as_uri() + (f"#{fragment}" if fragment else ""),
        ]
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s, check=False)
    probed.unlink(missing_ok=True)
    console = [ln for ln in proc.stderr.splitlines() if ":CONSOLE" in ln]
    m = _TITLE.search(proc.stdout)
    if m is None:
        return PageLoad(-1, -1, -1, console, screenshot)
    return PageLoad(int(m.group(1)), int(m.group(2)), int(m.group(3)), console, screenshot)
