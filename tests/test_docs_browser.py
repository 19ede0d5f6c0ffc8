"""The built documentation site, opened as a reader opens it: in headless Chromium,
with no network (the machine's, or CI's, which reaches no CDN).

Opened from the built folder (`file://`), on the conventions page, a pillar page, an
API page and a notebook page, after the page's scripts ran: every formula is typeset
by the MathJax shipped with the site (no raw TeX left in the visible text, no TeX
error), the notebook's figures are images the browser decoded, the API signatures
are formatted, and every link into the site names a file that exists (no folder, so
no directory listing) with the id its `#fragment` names. Served over HTTP, the search
finds a page. Screenshots are written to `docs-screenshots/` in the repository root,
so that a person can look.

Needs Debian's `chromium` (`apt-get install chromium`; `.ci/run` installs it). Where
it is missing the tests are skipped, except under `CONSTRAINED_JAX_REQUIRE_BROWSER=1`
(set by `.ci/run`), where they fail. `.ci/run` installs it while the tests run and
names, in `CONSTRAINED_JAX_BROWSER_INSTALL`, the file that receives apt's exit status
when the install ends: the tests wait for that file. The browser is driven through
the DevTools protocol over a pipe (`--remote-debugging-pipe`): no Python package is
needed.
"""

import base64
import functools
import http.server
import json
import os
import pathlib
import re
import select
import shutil
import subprocess
import sys
import tempfile
import threading
import time
import urllib.parse

import pytest

from .test_docs import needs_mkdocs


ROOT = pathlib.Path(__file__).parents[1]
SCREENSHOTS = ROOT / "docs-screenshots"
CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
REQUIRED = os.environ.get("CONSTRAINED_JAX_REQUIRE_BROWSER", "0") == "1"
INSTALL_STATUS = os.environ.get("CONSTRAINED_JAX_BROWSER_INSTALL")


def _wait_for_install(limit_s: float = 1200.0) -> None:
    """Where an install of Chromium is under way (`.ci/run`), wait for its end."""
    if not INSTALL_STATUS:
        return
    status = pathlib.Path(INSTALL_STATUS)
    deadline = time.monotonic() + limit_s
    while not status.exists():
        if time.monotonic() > deadline:
            pytest.fail(f"the Chromium install did not end in {limit_s:.0f} s")
        time.sleep(1.0)
    code = status.read_text().strip()
    if code != "0":
        log = status.with_name("chromium.log")
        tail = log.read_text()[-3000:] if log.exists() else ""
        pytest.fail(f"the Chromium install failed (apt exit status {code}):\n{tail}")


WIDTH, HEIGHT = 1280, 1600
PAGES = (
    "conventions.html",
    "extremize.html",
    "api/extremize.html",
    "notebooks/02_catenary_isoperimetric.html",
)
# `--no-sandbox`: CI runs as root. The background-networking flags keep Chromium
# from trying to reach its own services, which a closed network refuses.
FLAGS = (
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--hide-scrollbars",
    f"--window-size={WIDTH},{HEIGHT}",
)

# What a reader sees of the page, read in the page once its scripts ran. The text is
# the visible text outside code and typeset formulas, where no TeX may be left.
_READ_PAGE = """(() => {
  const skip = "script, style, noscript, template, pre, code, mjx-container, svg";
  const prose = [], cells = [];
  const walker = document.createTreeWalker(document.body, NodeFilter.SHOW_TEXT);
  for (let n = walker.nextNode(); n; n = walker.nextNode()) {
    const e = n.parentElement;
    if (!e || e.closest(skip) || !e.checkVisibility()) continue;
    prose.push(n.data);
    if (e.closest(".jp-RenderedMarkdown")) cells.push(n.data);
  }
  return {
    prose: prose.join(""),
    markdown_cells: cells.join(""),
    formulas: document.querySelectorAll("mjx-container svg").length,
    untypeset: [...document.querySelectorAll(".arithmatex")]
      .filter((e) => !e.querySelector("mjx-container svg"))
      .map((e) => e.textContent.slice(0, 80)),
    tex_errors: [...document.querySelectorAll("mjx-container [data-mjx-error]")]
      .map((e) => e.getAttribute("data-mjx-error")),
    figures: [...document.querySelectorAll(".jp-OutputArea-output img")]
      .map((i) => [i.complete, i.naturalWidth, i.naturalHeight]),
    signatures: [...document.querySelectorAll(".doc-signature")]
      .map((e) => e.innerText.trim()),
    links: [...document.querySelectorAll("a[href]")].map((a) => a.href),
  };
})()"""


class Browser:
    """Headless Chromium driven through the DevTools protocol: JSON messages, each
    ended by a NUL byte, on the file descriptors 3 (to Chromium) and 4 (from it)."""

    def __init__(self, chromium, profile):
        command = [chromium, *FLAGS, f"--user-data-dir={profile}"]
        command += ["--remote-debugging-pipe", "about:blank"]
        self.proc = subprocess.Popen(
            ["sh", "-c", 'exec "$@" 3<&0 4>&1 </dev/null >/dev/null', "sh", *command],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.DEVNULL,
        )
        self.buffer = b""
        self.last_id = 0
        self.session = None
        target = self.call("Target.createTarget", url="about:blank")["targetId"]
        attached = self.call("Target.attachToTarget", targetId=target, flatten=True)
        self.session = attached["sessionId"]
        self.call(
            "Emulation.setDeviceMetricsOverride",
            width=WIDTH,
            height=HEIGHT,
            deviceScaleFactor=1,
            mobile=False,
        )

    def close(self):
        try:
            self.call("Browser.close", timeout=10)
        except (RuntimeError, TimeoutError, OSError):
            pass
        try:
            self.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()

    def call(self, method, timeout=60, **params):
        self.last_id += 1
        message = {"id": self.last_id, "method": method, "params": params}
        if self.session is not None and not method.startswith(("Target.", "Browser.")):
            message["sessionId"] = self.session
        self.proc.stdin.write(json.dumps(message).encode() + b"\0")
        self.proc.stdin.flush()
        deadline = time.monotonic() + timeout
        while True:
            while b"\0" not in self.buffer:
                left = deadline - time.monotonic()
                if left <= 0 or not select.select([self.proc.stdout], [], [], left)[0]:
                    raise TimeoutError(f"Chromium did not answer {method}")
                chunk = os.read(self.proc.stdout.fileno(), 1 << 20)
                if not chunk:
                    raise RuntimeError(f"Chromium exited during {method}")
                self.buffer += chunk
            raw, self.buffer = self.buffer.split(b"\0", 1)
            reply = json.loads(raw)
            if reply.get("id") == self.last_id:  # (events have no id)
                if "error" in reply:
                    raise RuntimeError(f"{method}: {reply['error']}")
                return reply["result"]

    def evaluate(self, expression, await_promise=False):
        result = self.call(
            "Runtime.evaluate",
            expression=expression,
            returnByValue=True,
            awaitPromise=await_promise,
        )
        if "exceptionDetails" in result:
            raise RuntimeError(f"{expression[:80]}: {result['exceptionDetails']}")
        return result["result"].get("value")

    def wait_for(self, expression, timeout=30):
        """Wait (in real time) until `expression` is true in the page."""
        deadline = time.monotonic() + timeout
        while not self.evaluate(expression):
            if time.monotonic() > deadline:
                raise TimeoutError(f"never true: {expression}")
            time.sleep(0.1)

    def open(self, url):
        self.call("Page.navigate", url=url)
        self.wait_for(
            f"document.URL === {json.dumps(url)} && document.readyState === 'complete'"
        )

    def screenshot(self, path):
        data = self.call("Page.captureScreenshot", format="png")["data"]
        path.write_bytes(base64.b64decode(data))


@pytest.fixture(scope="module")
def browser():
    _wait_for_install()
    if not os.path.exists(CHROMIUM):
        message = f"no Chromium at {CHROMIUM}: apt-get install chromium"
        if REQUIRED:
            pytest.fail(message + " (CONSTRAINED_JAX_REQUIRE_BROWSER=1 requires it)")
        pytest.skip(message + " (.ci/run installs it)")
    with tempfile.TemporaryDirectory() as profile:
        browser = Browser(CHROMIUM, profile)
        try:
            yield browser
        finally:
            browser.close()


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    site = tmp_path_factory.mktemp("browser") / "site"
    proc = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict"]
        + ["--config-file", str(ROOT / "mkdocs.yml"), "--site-dir", str(site)],
        cwd=site.parent,
        env=dict(os.environ, NO_MKDOCS_2_WARNING="1"),
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return site


@pytest.fixture(scope="module")
def screenshots():
    SCREENSHOTS.mkdir(exist_ok=True)
    for old in SCREENSHOTS.glob("*.png"):
        old.unlink()
    print(f"\nscreenshots of the pages: {SCREENSHOTS}")
    return SCREENSHOTS


@functools.cache
def _ids(page: pathlib.Path) -> frozenset:
    return frozenset(re.findall(r'\sid="([^"]+)"', page.read_text()))


def _broken_links(site, links):
    """The links into the site that name no file (a folder, a missing file) or no
    id on the page they name. Links out of the site (http) are not followed."""
    broken = []
    for href in links:
        url = urllib.parse.urlsplit(href)
        if url.scheme != "file":
            continue
        target = pathlib.Path(urllib.parse.unquote(url.path))
        if not target.is_relative_to(site):
            broken.append(f"{href} (outside the site)")
        elif not target.is_file():
            broken.append(f"{href} ({'a folder' if target.is_dir() else 'missing'})")
        elif url.fragment and target.suffix == ".html":
            if urllib.parse.unquote(url.fragment) not in _ids(target):
                broken.append(f"{href} (no such id)")
    return broken


def _check_page(browser, site, screenshots, path):
    browser.open((site / path).as_uri())
    started = "window.MathJax && MathJax.startup && MathJax.startup.promise"
    loaded = browser.evaluate(f"!!({started})")
    if loaded:  # (wait until it typeset the page)
        browser.evaluate(f"{started}.then(() => true)", await_promise=True)
    name = path.replace("/", "_").removesuffix(".html")
    browser.screenshot(screenshots / f"{name}.png")  # (also of a failing page)
    assert loaded, "MathJax did not load"
    page = browser.evaluate(_READ_PAGE)

    # Formulas: typeset (SVG), none left as TeX, none with a TeX error.
    if path != "api/extremize.html":  # (its docstrings hold no formulas)
        assert page["formulas"] >= 5, page["formulas"]
    assert not page["untypeset"], page["untypeset"]
    assert not page["tex_errors"], page["tex_errors"]
    for raw in ("\\(", "\\)", "\\[", "\\]", "$$"):
        at = page["prose"].find(raw)
        assert at < 0, f"raw TeX in the text: {page['prose'][at - 80 : at + 80]!r}"
    broken = _broken_links(site, page["links"])
    assert not broken, broken
    # Not a link checker for the whole site: enough links to know they were read.
    assert len(page["links"]) > 30, page["links"]

    if path.startswith("api/"):
        # The signatures are formatted (by ruff): the long ones span several lines.
        long = [s for s in page["signatures"] if len(s) > 88]
        assert long, page["signatures"]
        assert all("\n" in s for s in long), long
    if path.startswith("notebooks/"):
        # The Markdown cells' `$...$` were typeset too, and the figures are images.
        at = page["markdown_cells"].find("$")
        assert at < 0, page["markdown_cells"][at - 80 : at + 80]
        figures = page["figures"]
        assert len(figures) >= 3, figures
        assert all(done and w > 200 and h > 100 for done, w, h in figures), figures
        # A second screenshot, at the first figure.
        browser.evaluate(
            "window.scrollTo(0, document.querySelector('.jp-OutputArea-output img')"
            ".getBoundingClientRect().top + window.scrollY - 200)"
        )
        time.sleep(0.5)  # (the header's title changes on scrolling, animated)
        browser.screenshot(screenshots / f"{name}_figure.png")


class _Quiet(http.server.SimpleHTTPRequestHandler):
    def log_message(self, *args):
        pass


def _check_search(browser, site, screenshots):
    """Served over HTTP (as by `mkdocs serve` or any web server), the search box
    finds the pages that hold a word. (Opened from the folder, the browser does not
    let the search's web worker read its index: search needs a server.)"""
    handler = functools.partial(_Quiet, directory=str(site))
    with http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler) as server:
        threading.Thread(target=server.serve_forever, daemon=True).start()
        try:
            port = server.server_address[1]
            # `?q=` opens the search box with the query typed in.
            browser.open(f"http://127.0.0.1:{port}/index.html?q=multiplier")
            browser.wait_for(
                "document.querySelectorAll('.md-search-result__item').length > 0"
            )
            results = browser.evaluate(
                "[...document.querySelectorAll('.md-search-result__item a')]"
                ".map((a) => a.getAttribute('href'))"
            )
            browser.screenshot(screenshots / "search.png")
        finally:
            server.shutdown()
    pages = {urllib.parse.urlsplit(r).path.lstrip("/") for r in results}
    assert "conventions.html" in pages, results
    assert all((site / page).is_file() for page in pages), results


@needs_mkdocs
def test_site_in_a_browser(browser, site, screenshots):
    """Each page of `PAGES` opened from the folder, then the search served. (One
    test, so that the site is built and the browser started once, on one worker.)"""
    failures = []
    for path in PAGES:
        try:
            _check_page(browser, site, screenshots, path)
        except (AssertionError, RuntimeError, TimeoutError) as e:
            failures.append(f"{path}: {type(e).__name__}: {e}")
    try:
        _check_search(browser, site, screenshots)
    except (AssertionError, RuntimeError, TimeoutError) as e:
        failures.append(f"search: {type(e).__name__}: {e}")
    assert not failures, "\n\n".join(failures) + f"\n(screenshots: {screenshots})"
