"""Reports as a person sees them: rendered by headless Chromium (Debian's chromium package; .ci/run
installs it). Checks that no table or figure runs off the page, that the headline verdict is there,
and takes a screenshot."""

import json
import re
import shutil
import subprocess
from pathlib import Path

import pytest

from castimate.report import write_report

ROOT = Path(__file__).resolve().parents[1]
WIDTH = 1024  # a laptop browser window, narrower than the page's 1200 px maximum

PROBE = """<script>
window.addEventListener('load', () => {
  const w = document.documentElement.clientWidth;
  const wide = [...document.querySelectorAll('table, figure img, pre')]
    .filter(e => e.getBoundingClientRect().right > w + 1).map(e => e.tagName + ':' + e.getBoundingClientRect().right);
  document.body.setAttribute('data-probe', JSON.stringify(
    {width: w, scroll: document.documentElement.scrollWidth, wide: wide,
     headline: (document.querySelector('p.headline') || {}).className || null}));
});
</script></body>"""


def chromium() -> str:
    exe = shutil.which("chromium") or shutil.which("chromium-browser")
    if exe is None:
        pytest.fail("chromium not found: apt-get install chromium (.ci/run does)")
    return exe


def render(html: Path, tmp: Path) -> tuple[dict, Path]:
    """Load the page headless at WIDTH px: the layout probe's findings and a screenshot, from one
    Chromium run (the probe only adds an attribute to the body once the page has loaded)."""
    probe = tmp / (html.stem + "_probe.html")
    probe.write_text(html.read_text().replace("</body>", PROBE))
    shot = tmp / (html.stem + ".png")
    dom = subprocess.run([chromium(), "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars",
                          f"--user-data-dir={tmp / 'profile'}", f"--window-size={WIDTH},900",
                          "--virtual-time-budget=5000", "--dump-dom", f"--screenshot={shot}", probe.as_uri()],
                         capture_output=True, text=True, timeout=120).stdout
    m = re.search(r"data-probe=\"([^\"]*)\"", dom)
    assert m, "the page did not finish loading in Chromium"
    return json.loads(m.group(1).replace("&quot;", '"')), shot


@pytest.mark.parametrize("solved", ["xsens_imutk", "mimu4444_exp1_static", "mimu4444_exp1_dynamic"])
def test_report_fits_a_browser_window(solved, tmp_path):
    d = tmp_path / solved
    shutil.copytree(ROOT / "reports" / solved, d)
    html = write_report(d, tmp_path / f"{solved}.html")
    probe, shot = render(html, tmp_path)
    assert probe["width"] <= WIDTH
    assert probe["wide"] == [] and probe["scroll"] <= probe["width"], probe
    assert probe["headline"] is not None
    assert shot.stat().st_size > 20_000 and shot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_a_dynamic_fit_far_above_the_noise_model_is_not_shown_as_success(tmp_path):
    """MIMU4444 exp_1 dynamic with white noise (``noise.motion_dependent: none``): IPOPT converged at
    χ²/dof ≈ 7500; the headline says the model does not fit. The bundled report (noise model, χ²/dof
    about 1) with the white fit's χ²/dof stands in for that solve."""
    d = tmp_path / "dyn"
    shutil.copytree(ROOT / "reports" / "mimu4444_exp1_dynamic", d)
    res = json.loads((d / "results.json").read_text())
    res["residuals"]["chi2_per_dof"] = 7509.0
    res["noise"].pop("motion_dependent", None)
    (d / "results.json").write_text(json.dumps(res))
    text = write_report(d).read_text()
    assert res["status"]["success"] is True and res["residuals"]["chi2_per_dof"] > 1000
    assert '<p class="headline bad">The model does not fit the data: χ²/dof = ' \
           f'{str(round(res["residuals"]["chi2_per_dof"]))[:2]}' in text
    assert '<td>solver status</td><td><span class="bad">converged</span>' in text and "castimate 0." in text
