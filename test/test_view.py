"""``view``: the web page, in a real browser (headless Chromium through Playwright).

- live: ``rig --view`` serves the page of a running rig; a screenshot shows
  the platform (not blank), and after a ``pose_setpoint`` step a second one
  shows the platform higher on the screen;
- bag: the same page replaying a bag, at the two ends of the time slider
  (moved with the keyboard, as a user would);
- a namespace with no rig: the page says so and the server keeps waiting;
- bad input without a browser: a port in use and a bag without poses give
  one line and exit 2.

The platform is found on a screenshot by its colour (the green plate).
Debian's ``chromium`` is used, never a downloaded browser. Where it (or
Playwright) is missing the browser tests skip, except under CI (``CI=true``),
where they fail: CI installs chromium. Screenshots are left in the test's
temporary directory (paths printed; run with ``-s``).
"""
from __future__ import annotations

import os
import re
import socket
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from ros_harness import PYTHON, wait_until

REPO = Path(__file__).resolve().parents[1]
#: every test here spawns a process (view, rig, plot, a browser)
pytestmark = pytest.mark.slow
CHROMIUM = '/usr/bin/chromium'
CHROMIUM_ARGS = ['--no-sandbox', '--enable-unsafe-swiftshader', '--use-angle=swiftshader',
                 '--disable-background-networking', '--disable-component-update',
                 '--disable-sync']
VIEWPORT = {'width': 900, 'height': 600}
#: Software WebGL on a loaded two-core machine: the first frame can take tens of seconds.
PAGE_TIMEOUT = 150.0
SHOT_TIMEOUT_MS = 150_000


# ------------------------------------------------------------------- helpers
@pytest.fixture
def browser(tmp_path):
    """A headless Chromium with a fresh profile (Playwright's persistent context)."""
    reason = ''
    if not os.path.exists(CHROMIUM):
        reason = 'chromium is not installed at %s (apt-get install chromium)' % CHROMIUM
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        reason = reason or 'playwright is not installed (make installs it)'
    if reason:
        if os.environ.get('CI') == 'true':
            pytest.fail('browser test under CI: ' + reason)
        pytest.skip(reason)
    with sync_playwright() as p:
        ctx = p.chromium.launch_persistent_context(
            str(tmp_path / 'chromium-profile'), executable_path=CHROMIUM, headless=True,
            args=CHROMIUM_ARGS, viewport=VIEWPORT)
        try:
            yield ctx
        finally:
            ctx.close()


def open_page(ctx, url, text):
    page = ctx.new_page()
    page.goto(url, timeout=PAGE_TIMEOUT * 1000)
    page.wait_for_selector('canvas', timeout=PAGE_TIMEOUT * 1000)
    page.get_by_text(text).first.wait_for(timeout=PAGE_TIMEOUT * 1000)
    return page


def shot(page, path, timeout=90.0):
    """A screenshot once the scene has faded in (the plate shows), or the
    last one taken when ``timeout`` s have passed."""
    from PIL import Image
    deadline = time.monotonic() + timeout
    while True:
        page.screenshot(path=str(path), timeout=SHOT_TIMEOUT_MS)
        img = np.asarray(Image.open(path).convert('RGB')).astype(int)
        if plate_pixels(img)[0].size > 100 or time.monotonic() > deadline:
            print('screenshot: %s' % path)
            return img
        time.sleep(1.0)


def scene_box(img):
    """The part of the page where the platform is drawn: left of the panel,
    clear of the orientation gizmo in the lower left corner."""
    h, w, _ = img.shape
    return img[int(0.08 * h):int(0.85 * h), int(0.12 * w):int(0.6 * w)]


def plate_pixels(img):
    """(rows, cols) of the green platform plate within ``scene_box``."""
    box = scene_box(img)
    r, g, b = box[..., 0], box[..., 1], box[..., 2]
    return np.nonzero((g > r + 40) & (g > b + 25))


def assert_not_blank(img):
    assert img.std() > 10, 'blank page'
    rows, _ = plate_pixels(img)
    assert rows.size > 100, 'no platform on the page (%d green pixels)' % rows.size


def plate_row(img) -> float:
    rows, _ = plate_pixels(img)
    return float(np.mean(rows))


def free_port() -> int:
    with socket.socket() as s:
        s.bind(('127.0.0.1', 0))
        return s.getsockname()[1]


def view_url(proc, timeout=120.0) -> str:
    found = []

    def ready():
        m = re.search(r'^(?:rig: live view at |view: )(http://\S+)', proc.stdout(), re.M)
        if m:
            found.append(m.group(1))
        return bool(found) or proc.returncode is not None
    wait_until(ready, timeout)
    assert found, proc.describe()
    return found[0]


def write_bag(path, with_poses=True, duration=2.0, rise=0.15):
    """A bag of a platform rising by ``rise`` over ``duration`` (50 Hz), with
    its leg lengths (inverse kinematics) and forces; without poses: forces only."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    from stewart63_ros.bagio import typestore
    from stewart63_ros.core.mechanics.kinematics import leg_lengths
    from stewart63_ros.core.plumbing.params import LEG_NAMES, load_mechanism
    mech = load_mechanism(REPO / 'config' / 'stewart63.yaml')
    ts = typestore()
    T = ts.types
    JS, PS = 'sensor_msgs/msg/JointState', 'geometry_msgs/msg/PoseStamped'

    def header(sec, nanosec):
        return T['std_msgs/msg/Header'](stamp=T['builtin_interfaces/msg/Time'](
            sec=sec, nanosec=nanosec), frame_id='base')

    def joints(h, position=(), effort=()):
        return T[JS](header=h, name=list(LEG_NAMES), position=np.array(position, float),
                     velocity=np.array([], float), effort=np.array(effort, float))
    writer = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP)
    writer.open()
    topics = {'leg_forces': JS}
    if with_poses:
        topics.update({'platform_pose': PS, 'leg_lengths': JS})
    conns = {topic: writer.add_connection('/' + topic, msgtype, typestore=ts)
             for topic, msgtype in topics.items()}
    for k in range(int(duration * 50) + 1):
        t = k / 50.0
        sec, nanosec = 100 + int(t), int(round((t % 1) * 1e9)) % 1_000_000_000
        stamp_ns = sec * 1_000_000_000 + nanosec
        h = header(sec, nanosec)
        forces = joints(h, effort=[300.0 * (1 + i) for i in range(6)])
        writer.write(conns['leg_forces'], stamp_ns, ts.serialize_cdr(forces, JS))
        if with_poses:
            position = np.array([0.0, 0.0, 1.0 + rise * t / duration])
            pose = T[PS](header=h, pose=T['geometry_msgs/msg/Pose'](
                position=T['geometry_msgs/msg/Point'](x=0.0, y=0.0, z=float(position[2])),
                orientation=T['geometry_msgs/msg/Quaternion'](x=0.0, y=0.0, z=0.0, w=1.0)))
            writer.write(conns['platform_pose'], stamp_ns, ts.serialize_cdr(pose, PS))
            lengths = joints(h, position=leg_lengths(mech, position, np.eye(3)))
            writer.write(conns['leg_lengths'], stamp_ns, ts.serialize_cdr(lengths, JS))
    writer.close()
    return path


def run_view(*args, timeout=60):
    import subprocess
    return subprocess.run([PYTHON, '-m', 'stewart63_ros.tools.view', *map(str, args)],
                          capture_output=True, text=True, timeout=timeout, cwd=REPO)


# ------------------------------------------------------------------- bad input
def test_port_in_use_is_a_clear_error():
    with socket.socket() as s:
        s.bind(('127.0.0.1', 0))
        s.listen()
        port = s.getsockname()[1]
        result = run_view('--port', port)
    assert result.returncode == 2, result.stderr
    assert 'port %d is in use' % port in result.stderr
    assert 'Traceback' not in result.stderr and len(result.stderr.strip().splitlines()) == 1


def test_bag_without_poses_says_what_it_lacks(tmp_path):
    bag = write_bag(tmp_path / 'forces_only', with_poses=False)
    result = run_view('--port', free_port(), bag)
    assert result.returncode == 2, result.stderr
    assert 'platform_pose' in result.stderr and 'it has: /leg_forces' in result.stderr
    assert 'Traceback' not in result.stderr


def test_rig_view_refuses_a_port_in_use():
    with socket.socket() as s:
        s.bind(('127.0.0.1', 0))
        s.listen()
        port = s.getsockname()[1]
        import subprocess
        result = subprocess.run([PYTHON, '-m', 'stewart63_ros.tools.rig', '--view',
                                 '--view-port', str(port), '--duration', '0.1'],
                                capture_output=True, text=True, timeout=60, cwd=REPO)
    assert result.returncode == 2
    assert 'in use' in result.stderr and 'Traceback' not in result.stderr


# ------------------------------------------------------------------- in a browser
def test_live_page_follows_a_pose_setpoint_step(ros, browser, tmp_path):
    from geometry_msgs.msg import PoseStamped
    from ros_harness import wait_matched
    from std_srvs.srv import SetBool

    from stewart63_ros import topics
    # lockstep: on a two-core machine the software-rendering browser can
    # starve a realtime loop (the controller's watchdog then withholds forces)
    rig = ros.python('-m', 'stewart63_ros.tools.rig', '--mode', 'lockstep', '--view',
                     '--view-port', str(free_port()), '--log-dir', str(tmp_path / 'rig'),
                     name='rig')
    node = ros.node('probe')
    pause = node.create_client(SetBool, 'plant/pause')

    def hold(paused: bool):
        assert ros.spin_until(pause.service_is_ready, 60), rig.describe()
        answer = pause.call_async(SetBool.Request(data=paused))
        assert ros.spin_until(answer.done, 30) and answer.result().success, answer.result()
    url = view_url(rig, timeout=240)
    page = open_page(browser, url, 'Live')
    # The lockstep rig runs flat out: paused while the page draws its first
    # frames in software, so that the two do not share the cores.
    hold(True)
    time.sleep(3.0)
    before = shot(page, tmp_path / 'live_before.png')
    assert_not_blank(before)
    hold(False)

    poses = []
    node.create_subscription(PoseStamped, 'platform_pose',
                             lambda m: poses.append(m.pose.position.z), 10)
    pub = node.create_publisher(PoseStamped, 'pose_setpoint', topics.SETPOINT_QOS)
    assert wait_matched(pub, 2, timeout=30)          # controller and fk
    assert ros.spin_until(lambda: poses, timeout=30)
    z0 = poses[-1]
    msg = PoseStamped()
    msg.header.frame_id = 'base'
    msg.pose.position.z = 1.16
    msg.pose.orientation.w = 1.0
    pub.publish(msg)
    assert ros.spin_until(lambda: poses[-1] > z0 + 0.07, timeout=30), (z0, poses[-1])
    time.sleep(3.0)                                 # the page follows at 30 Hz
    after = shot(page, tmp_path / 'live_after.png')
    assert_not_blank(after)
    diff = np.abs(scene_box(after) - scene_box(before)).sum(axis=2) > 60
    moved = plate_row(before) - plate_row(after)
    print('platform z %.3f -> %.3f m; plate %.1f px higher on the page; %d pixels changed'
          % (z0, poses[-1], moved, diff.sum()))
    assert diff.sum() > 200
    assert moved > 3.0
    assert rig.returncode is None, rig.describe()
    assert ros.stop(rig) == 0


def test_bag_page_at_two_slider_positions(browser, tmp_path):
    bag = write_bag(tmp_path / 'rising')
    proc = None
    try:
        import subprocess
        out = open(tmp_path / 'view.out', 'w')
        proc = subprocess.Popen([PYTHON, '-m', 'stewart63_ros.tools.view', '--port', '0',
                                 str(bag)], stdout=out, stderr=subprocess.STDOUT, cwd=REPO,
                                start_new_session=True)
        text = lambda: (tmp_path / 'view.out').read_text()  # noqa: E731
        assert wait_until(lambda: 'view: http' in text() or proc.poll() is not None, 120)
        url = re.search(r'view: (http://\S+)', text()).group(1)
        page = open_page(browser, url, 't = 0.000 s')
        time.sleep(2.0)
        start = shot(page, tmp_path / 'bag_start.png')
        assert_not_blank(start)
        slider = page.get_by_role('slider').first
        slider.focus()
        page.keyboard.press('End')
        page.get_by_text('t = 2.000 s').first.wait_for(timeout=PAGE_TIMEOUT * 1000)
        time.sleep(2.0)
        end = shot(page, tmp_path / 'bag_end.png')
        assert_not_blank(end)
        moved = plate_row(start) - plate_row(end)
        diff = np.abs(scene_box(end) - scene_box(start)).sum(axis=2) > 60
        print('bag: plate %.1f px higher at the end of the slider; %d pixels changed'
              % (moved, diff.sum()))
        assert diff.sum() > 200
        assert moved > 3.0
        assert proc.poll() is None, text()
    finally:
        if proc is not None and proc.poll() is None:
            proc.terminate()
            proc.wait(10)


class PageClient:
    """A client of the page over its websocket, as the browser is: it reads
    every update the view pushes (viser's frames: 16-byte sizes, then
    zstd-compressed msgpack) and sends what the page sends when the ghost's
    handle is dragged (viser's TransformControlsUpdateMessage)."""

    def __init__(self, url: str):
        import threading

        import viser
        from websockets.sync.client import connect
        self.ws = connect(url.replace('http://', 'ws://'),
                          subprotocols=['viser-v' + viser.__version__])
        self.texts = []
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self):
        import msgspec
        import zstandard
        try:
            for frame in self.ws:
                size, packed = (int.from_bytes(frame[k:k + 8], 'little') for k in (0, 8))
                inner = zstandard.ZstdDecompressor().decompress(frame[16:16 + packed],
                                                                max_output_size=size)
                for message in msgspec.msgpack.decode(inner)['messages']:
                    self.texts.append(str(message))
        except Exception:  # noqa: BLE001 - the view closed the connection: reading ends
            pass

    def drag(self, position, wxyz=(1.0, 0.0, 0.0, 0.0)):
        import msgspec
        from viser import _messages
        message = _messages.TransformControlsUpdateMessage(
            name='/setpoint_handle', wxyz=tuple(wxyz), position=tuple(position))
        self.ws.send(msgspec.msgpack.encode(message.as_serializable_dict()))

    def said(self, text: str) -> bool:
        return any(text in t for t in list(self.texts))


def test_dragging_the_ghost_publishes_a_pose_setpoint(setup, ros, tmp_path):
    """The handle at the ghost, dragged on the page, sends ``pose_setpoint``;
    a pose outside the stroke is refused on the page and not sent."""
    from geometry_msgs.msg import PoseStamped
    from ros_harness import wait_matched

    from stewart63_ros import topics
    got = []
    node = ros.node('probe')
    sub = node.create_subscription(PoseStamped, 'pose_setpoint', got.append,
                                   topics.SETPOINT_QOS)
    proc = ros.python('-m', 'stewart63_ros.tools.view', '--port', str(free_port()),
                      name='view')
    page = PageClient(view_url(proc))
    assert wait_matched(sub, 1, timeout=60)
    # the handle exists on the page (its scene message came) before it is dragged
    assert wait_until(lambda: page.said('/setpoint_handle'), 60), page.texts[-3:]
    target = np.asarray(setup.task.initial_position) + [0.02, -0.01, 0.05]
    page.drag(target)
    assert ros.spin_until(lambda: got, timeout=30), page.texts[-3:]
    p = got[-1].pose.position
    assert np.allclose([p.x, p.y, p.z], target, atol=1e-9) and got[-1].header.frame_id == 'base'
    assert wait_until(lambda: page.said('Sent: x %.3f' % target[0]), 10)
    # far above the stroke: refused on the page, nothing sent
    page.drag((0.0, 0.0, 3.0))
    assert wait_until(lambda: page.said('Refused'), 30), page.texts[-3:]
    assert page.said('outside the stroke')
    ros.spin_until(lambda: len(got) > 1, timeout=2.0)
    assert len(got) == 1, [m.pose.position for m in got]
    assert proc.returncode is None, proc.describe()
    assert ros.stop(proc) == 0


def test_page_says_when_there_is_no_rig(ros, browser, tmp_path):
    proc = ros.python('-m', 'stewart63_ros.tools.view', '--port', str(free_port()),
                      '--namespace', '/nobody_here', name='view')
    url = view_url(proc)
    page = open_page(browser, url, 'No rig in namespace')
    assert '/nobody_here' in page.content()
    page.screenshot(path=str(tmp_path / 'no_rig.png'), timeout=SHOT_TIMEOUT_MS)
    print('screenshot: %s' % (tmp_path / 'no_rig.png'))
    time.sleep(2.0)
    assert proc.returncode is None, proc.describe()     # still waiting
    assert 'Waiting' in page.content()


if __name__ == '__main__':
    sys.exit(pytest.main([__file__, '-v', '-s']))
