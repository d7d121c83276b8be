"""The HTML report of a tiny workflow run opened in a real browser (headless Chromium over the DevTools
Protocol, `headless_chromium.py`) at 1280 px width: a screenshot, every image decoded, no console
error or failed request, every section present with content, no horizontal overflow.

Chromium comes from Debian's packages (`scripts/install_browser.sh`, which `.ci/run` calls); the tests
are skipped, with one line saying so, only when no Chromium is found. Sections are found by their
`<h2>` titles (the enclosing `<section>` when there is one, else the elements up to the next `<h2>`),
images by `<img>`, so the checks do not depend on how the report is written.
"""

from __future__ import annotations

import io
import os
import re
import shutil
import uuid

import numpy as np
import pytest
from matplotlib import image as mpimg

from headless_chromium import Chromium, find_chromium
from workflow_runs import snakemake

# The report's section titles, as its <h2> elements say them (a leading "N." numbering is ignored).
# The dark and linearity run below shows every one: a stage that did not run keeps its section, which says so.
EXPECTED_SECTIONS = (
    "Summary",
    "Dark frames",
    "Linearity",
    "Geometry",
    "Roll-off",
    "Relative spectral response",
    "Absolute spectral radiance",
    "Immersion factor",
    "Field match-up",
    "Diagnostics",
    "Stages not run",
    "Provenance",
)
WIDTH_PX, HEIGHT_PX = 1280, 800
# a section has content when its text beyond the title has at least this many characters, or it holds an image
MIN_SECTION_TEXT_CHARS = 20

# every <h2>: its title, the text and images of its section (the enclosing <section>, else the siblings up
# to the next <h2>), and whether it is rendered at all
SECTIONS_JS = r"""
[...document.querySelectorAll('h2')].map(h => {
  const section = h.closest('section');
  let parts = [];
  if (section) {
    parts = [section];
  } else {
    for (let n = h.nextElementSibling; n && n.tagName !== 'H2' && !n.querySelector('h2'); n = n.nextElementSibling)
      parts.push(n);
  }
  const text = parts.map(p => p.innerText).join(' ').replace(h.innerText, '').trim();
  const images = parts.reduce((k, p) => k + (p.tagName === 'IMG' ? 1 : 0) + p.querySelectorAll('img').length, 0);
  const box = h.getBoundingClientRect();
  return {title: h.innerText.trim(), text_chars: text.length, images: images, rendered: box.width > 0 && box.height > 0};
})
"""
# every <img>, after the browser has decoded it (decode() rejects an image that cannot be decoded)
IMAGES_JS = r"""
Promise.all([...document.images].map((img, i) => img.decode().then(() => null, e => String(e)).then(err => ({
  index: i, src: img.src.slice(0, 60), error: err, natural_width: img.naturalWidth,
  natural_height: img.naturalHeight, shown_width: img.getBoundingClientRect().width,
  shown_height: img.getBoundingClientRect().height}))))
"""
# page width against the viewport, and the elements that reach past its right edge (with their section)
WIDTH_JS = r"""
(() => {
  const root = document.documentElement, limit = root.clientWidth;
  const wide = [...document.body.querySelectorAll('*')].filter(e => e.getBoundingClientRect().right > limit + 0.5)
    .filter(e => !e.parentElement || e.parentElement.getBoundingClientRect().right <= limit + 0.5 || e.parentElement === document.body)
    .slice(0, 8).map(e => {
      let h = e; while (h && h.tagName !== 'H2') h = h.previousElementSibling || h.parentElement;
      return e.tagName.toLowerCase() + ' ' + Math.round(e.getBoundingClientRect().width) + ' px wide, in "' +
        (h ? h.innerText.trim() : 'top of page') + '"';
    });
  return {scroll_width: root.scrollWidth, client_width: limit, inner_width: window.innerWidth, widest: wide};
})()
"""


def _title(text: str) -> str:
    return re.sub(r"^\d+(\.\d+)*\.?\s+", "", text).strip()


@pytest.fixture(scope="module")
def report_html(make_dataset, tmp_path_factory):
    """`results/report/index.html` of the cheapest real workflow run: the tiny dark and linearity
    experiments (the session's dataset of `test_workflow.py`, reused when on the same worker)."""
    src, _ = make_dataset([("dark_current", {}), ("shutter_offset", {})], seed=31)
    dataset = tmp_path_factory.mktemp("browser-data") / "dataset"
    shutil.copytree(src, dataset)
    workdir = tmp_path_factory.mktemp("browser-work")
    snakemake(workdir, dataset)
    return workdir / "results/report/index.html"


@pytest.fixture(scope="module")
def page(request, tmp_path_factory):
    """What the browser saw of the report, gathered in one visit (the browser closed after it)."""
    executable = find_chromium()
    if executable is None:
        where = (f"CHROMIUM={os.environ['CHROMIUM']} is not an executable" if os.environ.get("CHROMIUM")
                 else "no Chromium on the PATH")
        pytest.skip(f"{where}: run scripts/install_browser.sh (as .ci/run does) or set CHROMIUM to one")
    html = request.getfixturevalue("report_html")
    out = tmp_path_factory.mktemp("browser")
    browser = Chromium(executable, out / f"profile-{uuid.uuid4().hex}", WIDTH_PX, HEIGHT_PX, timeout_s=120.0)
    with browser:
        browser.open(html)
        seen = {"sections": browser.evaluate(SECTIONS_JS), "images": browser.evaluate(IMAGES_JS),
                "width": browser.evaluate(WIDTH_JS), "errors": browser.errors(),
                "n_img_tags": len(re.findall(r"<img\b", html.read_text(encoding="utf-8"), re.I))}
        shot = out / "report-1280px.png"
        shot.write_bytes(browser.screenshot_png())
        seen["screenshot"] = shot
    seen["leftover_pids"] = browser.leftover_pids_after_close
    return seen


def test_screenshot_is_a_non_blank_png(page):
    """The viewport at 1280 x 800 px as PNG, with the page drawn on it: the top of the report (title,
    contents, summary table) covers far more than 1 % of the viewport with non-background pixels, and a
    blank or failed render leaves a single colour."""
    png = page["screenshot"].read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n", f"{page['screenshot']} is not a PNG"
    pixels = np.round(mpimg.imread(io.BytesIO(png), format="png")[..., :3] * 255).astype(np.int32)
    assert pixels.shape[:2] == (HEIGHT_PX, WIDTH_PX)
    colours, counts = np.unique((pixels[..., 0] << 16) | (pixels[..., 1] << 8) | pixels[..., 2], return_counts=True)
    background_fraction = counts.max() / counts.sum()
    assert len(colours) > 2 and background_fraction < 0.99, (
        f"blank screenshot {page['screenshot']}: {len(colours)} colours, {background_fraction:.1%} background")


def test_every_image_is_decoded_and_non_empty(page):
    images = page["images"]
    assert len(images) == page["n_img_tags"] and len(images) > 0, (
        f"{len(images)} images in the page, {page['n_img_tags']} <img> tags in the file")
    bad = [im for im in images if im["error"] or im["natural_width"] <= 0 or im["natural_height"] <= 0
           or im["shown_width"] <= 0 or im["shown_height"] <= 0]
    assert not bad, f"{len(bad)} of {len(images)} images not decoded or empty: {bad[:3]}"


def test_no_console_errors_or_failed_requests(page):
    assert page["errors"] == [], "\n".join(page["errors"])


def test_every_expected_section_is_present_with_content(page):
    found = {_title(s["title"]): s for s in page["sections"]}
    missing = [t for t in EXPECTED_SECTIONS if t not in found]
    assert not missing, f"sections missing: {missing}; the page has {list(found)}"
    empty = [t for t in EXPECTED_SECTIONS
             if not found[t]["rendered"] or (found[t]["text_chars"] < MIN_SECTION_TEXT_CHARS
                                             and found[t]["images"] == 0)]
    assert not empty, f"sections without content (or not rendered): {empty}"


@pytest.mark.xfail(strict=True, reason="today's report overflows 1280 px: the Provenance section's table of "
                   "artefacts (a full 64-character config sha256 in each row, which cannot wrap) is 1292 px wide, "
                   "the page 1382 px (dark and linearity run)")
def test_no_horizontal_overflow_at_1280_px(page):
    width = page["width"]
    assert width["inner_width"] == WIDTH_PX
    assert width["scroll_width"] <= width["client_width"], (
        f"page {width['scroll_width']} px wide in a {width['client_width']} px viewport: {width['widest']}")


def test_the_browser_leaves_no_process_behind(page):
    assert page["leftover_pids"] == [], f"browser processes still running: {page['leftover_pids']}"
