"""play.py (play_server/app.py): the HTTP API the page uses (frames as PNG, the real world beside the model, one-line 400s on bad input)
and the page itself in a real headless browser (Debian's chromium through selenium)."""
import io
import socket
import threading
import time

import numpy as np
import pytest
from PIL import Image

pytest.importorskip("vizdoom")
from fastapi.testclient import TestClient  # noqa: E402

from sample_world import render as sw  # noqa: E402
from envs.world_model import WorldModelEnv  # noqa: E402
from envs.pairing import real_world_for  # noqa: E402
from play_server.app import PlaySession, build_app  # noqa: E402
from play_server.browser import headless_chromium  # noqa: E402
from tests.play_fixtures import tiny_play_world  # noqa: E402


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    return tiny_play_world(tmp_path_factory.mktemp("play"))


@pytest.fixture(scope="module")
def session(world):
    env = WorldModelEnv.from_checkpoint(world["model"], world["data"])
    real_env, raw_npz = real_world_for(env, str(world["data"]))
    assert real_env is not None, raw_npz
    s = PlaySession(env, real_env, raw_npz)
    s.reset(seed=0)
    yield s
    real_env.close()


@pytest.fixture(scope="module")
def client(session):
    return TestClient(build_app(session))


def png_array(content: bytes) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(content)).convert("RGB"))


def test_reset_and_step_return_png_frames_with_the_real_world_beside(client, session):
    response = client.post("/reset", json={"window": 1})
    assert response.status_code == 200 and response.headers["content-type"] == "image/png"
    assert response.headers["x-window"] == "1" and response.headers["x-step"] == "0"
    assert png_array(response.content).shape == (64, 64, 3)
    real = client.get("/real.png")
    assert real.status_code == 200
    with np.load(session.raw_npz) as npz:  # the real world starts at the window's last given frame, as recorded
        recorded = npz["frames"][session.env.window_start_frame(1)]
    np.testing.assert_array_equal(png_array(real.content), recorded)
    step = client.post("/step", json={"action": ["TURN_LEFT"]})
    assert step.status_code == 200 and step.headers["x-step"] == "1"
    assert not np.array_equal(png_array(client.get("/real.png").content), recorded)  # the real walker turned
    state = client.get("/state").json()
    assert state["buttons"] == list(sw.BUTTON_NAMES) and state["real_world"] and state["step"] == 1
    assert state["decoding"] == session.env.model.decoding.to_dict()
    assert client.post("/reset", json={"seed": 3}).status_code == 200
    assert client.post("/reset").status_code == 200  # an empty body: a start drawn at random


@pytest.mark.parametrize("body, reason", [
    ({"action": ["JUMP"]}, "unknown button(s) ['JUMP']: the buttons are ['MOVE_FORWARD'"),
    ({"action": "TURN_LEFT"}, "action:"),
    ({"act": ["TURN_LEFT"]}, "action: Field required"),
    ({"action": [], "speed": 2}, "speed: Extra inputs are not permitted"),
    (b'{"action": [', "malformed JSON body"),
    (b"", "malformed JSON body"),
])
def test_bad_step_requests_get_400_and_the_server_goes_on(client, body, reason):
    kwargs = {"content": body} if isinstance(body, bytes) else {"json": body}
    response = client.post("/step", **kwargs)
    assert response.status_code == 400
    error = response.json()["error"]
    assert reason in error and "\n" not in error
    assert client.post("/step", json={"action": ["MOVE_FORWARD"]}).status_code == 200


@pytest.mark.parametrize("body, reason", [
    ({"window": 10**6}, "window must be an integer in [0, "),
    ({"window": "two"}, "window: Input should be a valid integer"),
    ({"seed": 1, "window": 1}, "give seed or window, not both"),
])
def test_bad_reset_requests_get_400(client, body, reason):
    response = client.post("/reset", json=body)
    assert response.status_code == 400 and reason in response.json()["error"]


def test_the_page_is_served(client):
    page = client.get("/")
    assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
    assert all(f'"{path}"' in page.text for path in ("/step", "/reset", "/state"))


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def browser_or_skip():
    browser, reason = headless_chromium()
    if browser is None:
        pytest.skip(reason)
    return browser


def settled_steps(browser, By, timeout: float = 20.0) -> int:
    """The page's step counter once it has stopped changing for half a second."""
    deadline = time.time() + timeout
    last = int(browser.find_element(By.ID, "step").text)
    while time.time() < deadline:
        time.sleep(0.5)
        now = int(browser.find_element(By.ID, "step").text)
        if now == last:
            return now
        last = now
    raise AssertionError(f"the page kept stepping for {timeout} s with no key held")


def test_page_plays_in_a_headless_browser(session):
    import uvicorn

    port = free_port()
    server = uvicorn.Server(uvicorn.Config(build_app(session), host="127.0.0.1", port=port, log_level="warning"))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    browser = None
    try:
        while not server.started:
            time.sleep(0.05)
        browser = browser_or_skip()
        from selenium.webdriver.common.action_chains import ActionChains
        from selenium.webdriver.common.by import By
        from selenium.webdriver.common.keys import Keys
        from selenium.webdriver.support.ui import WebDriverWait

        browser.get(f"http://127.0.0.1:{port}/")
        wait = WebDriverWait(browser, 30)
        model = browser.find_element(By.ID, "model")
        wait.until(lambda b: (model.get_attribute("src") or "").startswith("blob:"))
        first_src = model.get_attribute("src")
        assert browser.find_element(By.ID, "step").text == "0"
        assert browser.find_element(By.ID, "real-view").is_displayed()  # the real world beside the model
        buttons = [b.text for b in browser.find_elements(By.CSS_SELECTOR, "#action-buttons button")]
        assert buttons == list(sw.BUTTON_NAMES)
        ActionChains(browser).key_down(Keys.ARROW_LEFT).pause(1.5).key_up(Keys.ARROW_LEFT).perform()
        wait.until(lambda b: int(b.find_element(By.ID, "step").text) >= 1)
        assert model.get_attribute("src") != first_src  # a new frame came in
        steps = settled_steps(browser, By)  # the request in flight when the key came up has landed
        time.sleep(1.0)
        assert int(browser.find_element(By.ID, "step").text) == steps  # the world waits while no key is held
        assert float(browser.find_element(By.ID, "fps").text) > 0
        assert "TURN_LEFT" not in browser.find_element(By.ID, "error").text
        browser.find_element(By.TAG_NAME, "body").send_keys("r")  # R: a new start
        wait.until(lambda b: b.find_element(By.ID, "step").text == "0")
    finally:
        if browser is not None:
            browser.quit()
        server.should_exit = True
        thread.join(timeout=10)
