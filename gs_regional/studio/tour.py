"""Drive the studio (`launch.py --studio`) in headless Chromium through its steps, time them as the
page sees them, and keep a screenshot of each step (docs/studio.png is the one after Select region).

    python scripts/studio_tour.py [--config configs/demo.yaml] [--out outputs/studio_tour]
        [--screenshot docs/studio.png] [--thresholds 0.4,0.6] [--edit] [--max-gaussians N] [key=value ...]

Times: Select region -> the highlighted count on the page, and each threshold move -> its new
count (the highlight's colours are sent before the count, on the same connection); the server's
own seconds beside them. Needs the 'viewer' extra, playwright and a Chromium ($CHROMIUM or on PATH).
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import time
from pathlib import Path

# Chromium without a GPU: WebGL through its software renderer (SwiftShader); the background-networking
# flags keep it from calling Google's hosts on a machine with a closed network (the tests use these too).
CHROMIUM_ARGS = ["--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist", "--no-sandbox",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync"]


def field(page, label):
    return page.locator(f"xpath=//label[normalize-space()='{label}']"
                        "/ancestor::div[contains(@class,'mantine-Flex-root')][1]//input[not(@type='hidden')]")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--config", default="configs/demo.yaml")
    p.add_argument("--out", default="outputs/studio_tour", help="exp_root_dir of the runs and the screenshots")
    p.add_argument("--instruction", default=None, help="default: the config's system.prompt")
    p.add_argument("--thresholds", default="0.4,0.6", help="comma-separated thresholds to move to, in turn")
    p.add_argument("--edit", action="store_true", help="also Edit and wait for it")
    p.add_argument("--screenshot", default=None, help="copy the Select region screenshot here (docs/studio.png)")
    p.add_argument("--max-gaussians", type=int, default=None, help="shown in the browser (default: the studio's)")
    p.add_argument("--port", type=int, default=8093)
    args, overrides = p.parse_known_args(argv)

    from playwright.sync_api import sync_playwright

    from gs_regional.api import _config_path
    from gs_regional.launch.logs import setup_logging
    from gs_regional.launch.view import DEFAULT_MAX_GAUSSIANS
    from gs_regional.studio.page import serve
    from gs_regional.studio.session import StudioSession

    out = Path(args.out).resolve()
    shots = out / "screenshots"
    shots.mkdir(parents=True, exist_ok=True)
    setup_logging(verbose=False)
    t0 = time.perf_counter()
    session = StudioSession.open(_config_path(args.config), [f"exp_root_dir={out}", *overrides])
    studio = serve(session, port=args.port, max_gaussians=args.max_gaussians or DEFAULT_MAX_GAUSSIANS)
    report = {"config": args.config, "overrides": overrides, "gaussians": session.n,
              "open_seconds": round(time.perf_counter() - t0, 2)}
    chromium = shutil.which(os.environ.get("CHROMIUM") or "chromium") or shutil.which("chromium-browser")
    try:
        with sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=chromium, args=CHROMIUM_ARGS)
            page = browser.new_page(viewport={"width": 1280, "height": 860})
            page.goto(studio.url)
            field(page, "Instruction").fill(args.instruction or session.prompt)
            page.get_by_text("Status: ready").wait_for(timeout=120_000)
            notice = page.locator(".mantine-Notification-closeButton")  # the software-WebGL notice
            page.wait_for_timeout(2000)
            if notice.count():
                notice.first.click()
            page.wait_for_timeout(3000)  # the splats drawn once
            t = time.perf_counter()
            page.get_by_role("button", name="Select region").click()
            page.get_by_text("UNet evaluations so far").wait_for(timeout=900_000)
            report["select_to_highlight_seconds"] = round(time.perf_counter() - t, 2)
            report["select_server_seconds"] = round(studio.page.shown_times.get("select_seconds", float("nan")), 2)
            report["selected"] = session.count
            page.wait_for_timeout(4000)
            page.screenshot(path=str(shots / "1_select_region.png"))
            report["thresholds"] = []
            for value in [float(v) for v in args.thresholds.split(",") if v.strip()]:
                box = field(page, "Threshold")
                t = time.perf_counter()
                box.fill(str(value))
                box.press("Enter")
                page.get_by_text(f"(threshold {value}").wait_for(timeout=120_000)
                report["thresholds"].append({
                    "threshold": value, "selected": session.count, "to_highlight_seconds": round(time.perf_counter() - t, 3),
                    "server_seconds": round(studio.page.shown_times.get("threshold_seconds", float("nan")), 4)})
            page.wait_for_timeout(3000)
            page.screenshot(path=str(shots / "2_threshold.png"))
            if args.edit:
                t = time.perf_counter()
                page.get_by_role("button", name="Edit", exact=True).click()
                page.get_by_text("Status: Edit: Done").wait_for(timeout=3_600_000)
                report["edit_seconds"] = round(time.perf_counter() - t, 1)
                report["edit_trial"] = str(session.edit_trial)
                page.wait_for_timeout(4000)
                page.screenshot(path=str(shots / "3_edited.png"))
            browser.close()
    finally:
        studio.stop()
    if args.screenshot:
        shutil.copyfile(shots / "1_select_region.png", args.screenshot)
    (out / "tour.json").write_text(json.dumps(report, indent=2))
    print(json.dumps(report, indent=2))
    return 0

