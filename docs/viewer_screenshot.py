"""Makes docs/viewer.png: the web map on the demo's Paris map at 1,500 m, speed layer,
flows and the tube of the demo's routes (std below 40 m/s).

make demo && .venv/bin/python docs/viewer_screenshot.py   # needs Debian's chromium
"""

from pathlib import Path

from playwright.sync_api import sync_playwright

from clients.local import LocalService

#: headless, WebGL on the CPU (SwiftShader), as tests/service/test_viewer.py runs it
FLAGS = ["--headless", "--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader"]
FLAGS += ["--disable-quic", "--no-first-run", "--disable-background-networking", "--disable-sync"]

if __name__ == "__main__":
    with LocalService("demo-output/bdf-data") as svc, sync_playwright() as p:
        page = p.chromium.launch(executable_path="/usr/bin/chromium", args=FLAGS).new_page(
            viewport={"width": 1280, "height": 820}
        )
        page.goto(f"{svc.url}/viewer?region=paris&alt_m=1500&layer=speed&max_std_mps=40&flows=1&tube=1")
        page.wait_for_selector("#map[data-drawn='paris@1500/speed']", timeout=120_000)
        page.wait_for_timeout(5000)  # the view's tiles
        box = page.locator("#map").bounding_box()
        page.mouse.click(box["x"] + box["width"] * 0.55, box["y"] + box["height"] * 0.45)
        page.wait_for_selector("#answer[data-answered]")
        page.screenshot(path=Path(__file__).with_name("viewer.png"))
        print(page.url)
