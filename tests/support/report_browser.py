"""The HTML report opened in a real browser (headless Chromium over the DevTools Protocol,
`headless_chromium.py`) at 1280 px width: a screenshot, every image decoded, no console
error or failed request, every section present with content, no horizontal overflow.

Chromium comes from Debian's packages (`scripts/install_browser.sh`, which `.ci/run` calls); the tests
are skipped, with one line saying so, only when no Chromium is found. Sections are found by their
`<h2>` titles (the enclosing `<section>` when it holds that title only, else the elements up to the
next `<h2>`), images by `<img>`, so the checks do not depend on how the report is written. The list of
titles is EXPECTED_SECTIONS below.

The tests are collected in test_workflow_default.py, on the report of its default tiny run (every stage
and the field hour), so that no workflow runs for them alone.
"""

from __future__ import annotations

import io
import os
import re
import uuid

import numpy as np
import pytest
from matplotlib import image as mpimg

from headless_chromium import Chromium, find_chromium

# The report's section titles, as its <h2> elements say them (a leading "N." numbering is ignored).
# The default tiny run (every experiment) shows every one.
EXPECTED_SECTIONS = (
    "Summary",
    "Dark frames",
    "Linearity",
    "Geometry",
    "Roll-off",
    "Relative spectral response",
    "Absolute spectral radiance",
    "Immersion factor",
    "Noise floor and limit of detection",
    "Field match-up",
    "Diagnostics: where the model fails",
    "Provenance",
)
WIDTH_PX, HEIGHT_PX = 1280, 800
# a section has content when its text beyond the title has at least this many characters, or it holds an image
MIN_SECTION_TEXT_CHARS = 20

# every <h2>: its title, the text and images of its section (the enclosing <section> when this is its only
# <h2>, else the siblings up to the next <h2>), and whether it is rendered at all
SECTIONS_JS = r"""
[...document.querySelectorAll('h2')].map(h => {
  const section = h.closest('section');
  let parts = [];
  if (section && section.querySelectorAll('h2').length === 1) {
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


# A page with one fault of each kind the checks look for, visited by the same browser after the report: each
# check must find its fault there, so that a check which cannot fail (a protocol event no longer sent, a
# script that finds nothing) does not pass unnoticed.
BROKEN_PAGE = """<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>faults</title>
<script>console.error("deliberate console error");</script></head>
<body style="margin:0">
<section><h2>1. Full</h2><p>This section has text enough to count as content, and two broken images.</p>
<img alt="truncated" src="data:image/png;base64,iVBORw0KGgoAAAANSUhEUgAAAAEAAAAB">
<img alt="absent" src="no-such-figure.png">
<div style="width:2000px">a block wider than the viewport</div></section>
<h2>2. Empty</h2>
<section><h2>3. Empty section</h2></section>
<h2>4. Bare</h2><p>A title without a section element, followed by text enough to count.</p>
</body></html>
"""


def _visit(browser: Chromium, html) -> dict:
    """What the browser sees of one page: sections, decoded images, widths, errors, <img> tags in the file."""
    browser.open(html)
    return {"sections": browser.evaluate(SECTIONS_JS), "images": browser.evaluate(IMAGES_JS),
            "width": browser.evaluate(WIDTH_JS), "errors": browser.errors(),
            "n_img_tags": len(re.findall(r"<img\b", html.read_text(encoding="utf-8"), re.I))}


def _image_problems(seen: dict) -> list[str]:
    images = seen["images"]
    problems = [] if len(images) == seen["n_img_tags"] else [
        f"{len(images)} images in the page, {seen['n_img_tags']} <img> tags in the file"]
    problems += [f"image {im['index']} ({im['src']}...): {im['error'] or 'empty'}, natural "
                 f"{im['natural_width']} x {im['natural_height']} px, shown {im['shown_width']:.0f} x "
                 f"{im['shown_height']:.0f} px" for im in images
                 if im["error"] or min(im["natural_width"], im["natural_height"], im["shown_width"],
                                       im["shown_height"]) <= 0]
    return problems


def _section_problems(seen: dict, expected: tuple[str, ...]) -> list[str]:
    found = {_title(s["title"]): s for s in seen["sections"]}
    problems = [f"section '{t}' missing (the page has {list(found)})" for t in expected if t not in found]
    problems += [f"section '{t}' not rendered or without content ({found[t]['text_chars']} characters, "
                 f"{found[t]['images']} images)" for t in expected if t in found
                 and (not found[t]["rendered"]
                      or (found[t]["text_chars"] < MIN_SECTION_TEXT_CHARS and found[t]["images"] == 0))]
    return problems


def _overflow(seen: dict) -> str | None:
    width = seen["width"]
    if width["scroll_width"] <= width["client_width"]:
        return None
    return f"page {width['scroll_width']} px wide in a {width['client_width']} px viewport: {width['widest']}"


def browse(html, out) -> dict:
    """What the browser saw of the report ``html`` and of the page of faults, in one browser (closed after);
    the test is skipped, with one line saying why, when no Chromium is found."""
    executable = find_chromium()
    if executable is None:
        where = (f"CHROMIUM={os.environ['CHROMIUM']} is not an executable" if os.environ.get("CHROMIUM")
                 else "no Chromium on the PATH")
        pytest.skip(f"{where}: run scripts/install_browser.sh (as .ci/run does) or set CHROMIUM to one")
    broken = out / "faults.html"
    broken.write_text(BROKEN_PAGE, encoding="utf-8")
    browser = Chromium(executable, out / f"profile-{uuid.uuid4().hex}", WIDTH_PX, HEIGHT_PX, timeout_s=120.0)
    with browser:
        seen = _visit(browser, html)
        shot = out / "report-1280px.png"
        shot.write_bytes(browser.screenshot_png())
        seen["screenshot"] = shot
        seen["faults"] = _visit(browser, broken)
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
    assert page["n_img_tags"] > 0, "the report has no <img>"
    problems = _image_problems(page)
    assert not problems, "\n".join(problems)


def test_no_console_errors_or_failed_requests(page):
    assert page["errors"] == [], "\n".join(page["errors"])


def test_every_expected_section_is_present_with_content(page):
    problems = _section_problems(page, EXPECTED_SECTIONS)
    assert not problems, "\n".join(problems)


def test_no_horizontal_overflow_at_1280_px(page):
    assert page["width"]["inner_width"] == WIDTH_PX
    overflow = _overflow(page)
    assert overflow is None, overflow


def test_each_check_finds_its_fault_on_a_page_made_to_fail(page):
    """The page of faults: both images (a truncated PNG, a missing file) fail, the console error and the
    failed request are reported, the two empty sections (a bare <h2>, a <section>) are found empty, the two
    full ones (likewise) full, and the 2000 px block overflows."""
    faults = page["faults"]
    assert len(_image_problems(faults)) == 2, _image_problems(faults)
    errors = "\n".join(faults["errors"])
    assert "console.error: deliberate console error" in errors, errors
    assert any(e.startswith("request failed:") and e.endswith("no-such-figure.png") for e in faults["errors"]), errors
    assert _section_problems(faults, ("Full", "Empty", "Empty section", "Bare", "Absent")) == [
        "section 'Absent' missing (the page has ['Full', 'Empty', 'Empty section', 'Bare'])",
        "section 'Empty' not rendered or without content (0 characters, 0 images)",
        "section 'Empty section' not rendered or without content (0 characters, 0 images)"]
    assert _overflow(faults) is not None and "2000 px wide" in _overflow(faults)


def test_the_browser_leaves_no_process_behind(page):
    assert page["leftover_pids"] == [], f"browser processes still running: {page['leftover_pids']}"
