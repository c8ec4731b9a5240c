"""Makes docs/viewer.png: the viewer on the demo's Paris map, tube layer at 1,500 m.

make demo && .venv/bin/python docs/viewer_screenshot.py   # needs Debian's chromium
"""

from pathlib import Path

from playwright.sync_api import sync_playwright

from clients.local import LocalService

FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run"]
FLAGS += ["--disable-background-networking", "--disable-component-update", "--disable-sync"]

if __name__ == "__main__":
    with LocalService("demo-output/bdf-data") as svc, sync_playwright() as p:
        page = p.chromium.launch(executable_path="/usr/bin/chromium", args=FLAGS).new_page(
            viewport={"width": 1000, "height": 760}
        )
        page.goto(f"{svc.url}/viewer")
        page.wait_for_selector("#image[data-alt-m]")
        page.fill("#maxStd", "59")  # the demo's tube bound, m/s
        page.dispatch_event("#maxStd", "change")
        page.select_option("#layer", "tube")
        page.wait_for_selector("#image[data-layer='tube']")
        page.eval_on_selector("#alt", "e => { e.value = 1500; e.dispatchEvent(new Event('change')); }")
        page.wait_for_selector("#image[data-alt-m='1500']")
        page.screenshot(path=Path(__file__).with_name("viewer.png"))
        print(page.text_content("#status"))
