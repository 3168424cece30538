"""fetchsync snapshot: the collector set, and snapshots of the real-sshd robot (this machine).

The ROS tests install a fake ROS 1 / ROS 2 under a temporary directory and
point the probe there (``ros_root``), so nothing is written to /opt. The sudo
tests create a throwaway non-root account with a password and a sudoers entry
(root only), log in as it, and feed the password to the real sudo.
"""

from __future__ import annotations

import json
import os
import re
import secrets
import shutil
import subprocess
import tarfile
import threading
import traceback
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from click.testing import CliRunner
from sshd import SSHHome

from fetchsync.chores.snapshot import (
    DEFAULT_COLLECTORS,
    MISSING,
    OK,
    STATUSES,
    Collector,
    RobotInfo,
    RosInstall,
    SudoPlan,
    archive_name,
    classify,
    load_config,
    parse_extra,
    parse_probe,
    remote_command,
    select_collectors,
    take_snapshot,
)
from fetchsync.cli import cli
from fetchsync.errors import ConfigError, UsageError

SYSTEM_NAMES = [c.name for c in DEFAULT_COLLECTORS if c.kind == "system"]


def read_archive(path: Path) -> tuple[dict[str, Any], dict[str, bytes]]:
    """(manifest, {name under the top directory: content})."""
    files: dict[str, bytes] = {}
    with tarfile.open(path, "r:gz") as tar:
        tops = {m.name.split("/", 1)[0] for m in tar.getmembers()}
        assert len(tops) == 1, tops
        for m in tar.getmembers():
            if m.isfile():
                f = tar.extractfile(m)
                assert f is not None
                files[m.name.split("/", 1)[1]] = f.read()
    return json.loads(files["manifest.json"]), files


def by_name(manifest: dict[str, Any]) -> dict[str, dict[str, Any]]:
    return {e["name"]: e for e in manifest["commands"]}


def only_archive(directory: Path) -> Path:
    found = list(directory.glob("snapshot-*.tar.gz"))
    assert len(found) == 1, found
    return found[0]


# --- the set, without a robot --------------------------------------------------------------------


def test_default_set_is_valid_and_covers_the_issue():
    for c in DEFAULT_COLLECTORS:
        c.validate()
    names = set(SYSTEM_NAMES)
    assert {
        "uname",
        "os_release",
        "uptime",
        "meminfo",
        "df",
        "top",
        "dmesg",
        "journal",
        "ip_addr",
        "ip_route",
        "lsusb",
        "lspci",
        "dpkg_ros",
    } <= names
    shared = {"ros_nodes", "ros_topics", "ros_services", "ros_params"}
    assert {c.name for c in DEFAULT_COLLECTORS if c.kind == "ros1"} == shared
    # ROS 2 adds its doctor's report and the logs (issue 26)
    assert {c.name for c in DEFAULT_COLLECTORS if c.kind == "ros2"} == shared | {
        "ros_doctor",
        "ros_log",
    }
    assert {c.name for c in DEFAULT_COLLECTORS if c.needs_sudo} == {"dmesg", "journal"}


def test_only_skip_extra_and_replacing_a_default():
    chosen = select_collectors(only=["uname", "ros_nodes"], extra=[parse_extra("x=echo 1")])
    assert [(c.name, c.kind) for c in chosen] == [
        ("uname", "system"),
        ("ros_nodes", "ros1"),
        ("ros_nodes", "ros2"),
        ("x", "system"),
    ]
    chosen = select_collectors(skip=["ros_nodes", "dmesg"])
    assert "dmesg" not in {c.name for c in chosen} and "ros_nodes" not in {c.name for c in chosen}
    # an extra with a default's name replaces it (both ROS variants), in place
    chosen = select_collectors(extra=[parse_extra("ros_nodes=echo mine")])
    assert [c.command for c in chosen if c.name == "ros_nodes"] == ["echo mine"]
    with pytest.raises(UsageError, match="no collector named unamee"):
        select_collectors(only=["unamee"])
    for bad in ("nocommand", "=x", "a b=x", "../x=y", "rosbag=x", "x="):
        with pytest.raises(UsageError):
            parse_extra(bad)


def test_config_file_toml_and_json(tmp_path):
    toml = tmp_path / "snap.toml"
    toml.write_text(
        'skip = ["lspci"]\n[[collectors]]\nname = "charger"\n'
        'command = "rosrun fetch_drivers read_board 0x3f"\nkind = "ros1"\n'
        "timeout = 20\nneeds_sudo = true\n"
    )
    cfg = load_config(toml)
    chosen = select_collectors(config=cfg)
    assert (
        Collector("charger", "rosrun fetch_drivers read_board 0x3f", 20.0, True, "ros1") in chosen
    )
    assert "lspci" not in {c.name for c in chosen}
    js = tmp_path / "snap.json"
    js.write_text(json.dumps({"defaults": False, "collectors": [{"name": "a", "command": "true"}]}))
    assert select_collectors(config=load_config(js)) == (Collector("a", "true"),)
    for text in (
        '{"collectors": [{"name": "a"}]}',
        '{"bogus": 1}',
        "[1]",
        '{"collectors": [{"name": "a", "command": "x", "kind": "ros3"}]}',
        '{"collectors": [{"name": "a", "command": "x", "timeout": 0}]}',
    ):
        js.write_text(text)
        with pytest.raises(ConfigError):
            load_config(js)


def test_classify():
    assert classify(0, b"") == OK
    assert classify(127, b"sh: 1: nope: not found\n") == MISSING
    assert classify(1, b"bash: line 1: nope: command not found\n") == MISSING
    assert classify(1, b"cat: /x: No such file or directory\n") == "failed"
    assert classify(124, b"", timeout=5, elapsed=5.2) == "timeout"
    assert classify(124, b"", timeout=5, elapsed=0.1) == "failed"  # its own 124, not timeout's


def test_probe_output_parsing_ignores_login_noise_and_picks_a_distro():
    info = parse_probe(
        "Welcome!\nuid=1000\nuser=fetch\ntimeout=yes\nsudo=password\n"
        "ros=1 /opt/ros/melodic\nros=1 /opt/ros/noetic\nros_distro=\n"
    )
    assert (info.uid, info.user, info.has_timeout, info.sudo) == (1000, "fetch", True, "password")
    assert info.ros == RosInstall(1, "noetic", "/opt/ros/noetic")
    info = parse_probe("uid=0\nros=1 /opt/ros/noetic\nros=2 /opt/ros/foxy\nros_distro=foxy\n")
    assert info.ros == RosInstall(2, "foxy", "/opt/ros/foxy") and info.sudo is None


def test_sudo_command_line_never_holds_the_password():
    password = "hunter2-" + secrets.token_hex(8)
    plan = SudoPlan("password", password=password.encode())
    info = RobotInfo(uid=1000, user="fetch", has_timeout=True, sudo="password", ros=None)
    line = remote_command(Collector("dmesg", "dmesg", needs_sudo=True), info=info, sudo=plan)
    assert password not in line and password not in repr(plan)
    assert line.startswith("sudo -S -p '' -- timeout -k 2 10 sh -c ")
    assert "exec </dev/null; dmesg" in line
    assert plan.stdin() == password.encode() + b"\n"
    plain = remote_command(Collector("uname", "uname -a"), info=info, sudo=plan)
    assert "sudo" not in plain


def test_archive_name():
    import datetime as dt

    when = dt.datetime(2026, 3, 4, 5, 6, 7)
    assert archive_name("fetch7.local", when) == "snapshot-fetch7.local-20260304-050607.tar.gz"
    assert archive_name("a b/c", when) == "snapshot-a_b_c-20260304-050607.tar.gz"


def test_list_needs_no_robot():
    result = CliRunner().invoke(cli, ["snapshot", "--list", "--only", "uname", "--json"])
    assert result.exit_code == 0, _why(result)
    assert json.loads(result.output) == [
        {
            "name": "uname",
            "kind": "system",
            "timeout": 10.0,
            "needs_sudo": False,
            "command": "uname -a",
        }
    ]


# --- against the real sshd robot -----------------------------------------------------------------


@pytest.fixture
def snap_env(
    ssh_home: SSHHome, clean_process_env: None, monkeypatch: pytest.MonkeyPatch
) -> SSHHome:
    monkeypatch.setenv("FETCHSYNC_ROBOT", "robot")
    return ssh_home


def run_cli(*args: str, env: dict[str, str] | None = None) -> Any:
    result = CliRunner().invoke(cli, ["snapshot", *args], env=env)
    if result.exception and not isinstance(result.exception, SystemExit):
        raise result.exception
    return result


@pytest.mark.slow
@pytest.mark.ssh
def test_default_snapshot_lists_every_system_command(snap_env, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    result = run_cli()
    assert result.exit_code == 0, _why(result)
    archive = only_archive(tmp_path)
    assert re.fullmatch(r"snapshot-robot-\d{8}-\d{6}\.tar\.gz", archive.name)
    summary = result.stdout.strip().splitlines()[-1]
    assert re.match(
        r"snapshot: \d+ ok, \d+ failed, \d+ missing.*; " + re.escape(archive.name) + r" \(\d",
        summary,
    ), summary
    manifest, files = read_archive(archive)
    entries = by_name(manifest)
    assert [n for n in entries if n in SYSTEM_NAMES] == SYSTEM_NAMES
    for entry in manifest["commands"]:
        assert entry["status"] in STATUSES
        assert {"name", "command", "exit_code", "duration", "status", "bytes"} <= set(entry)
    assert entries["uname"]["status"] == OK and files["uname.txt"].startswith(b"Linux")
    assert entries["uname"]["bytes"] == len(files["uname.txt"])
    assert entries["meminfo"]["status"] == OK and b"MemTotal" in files["meminfo.txt"]
    # this machine has no ROS: the ROS commands are listed once each, skipped
    assert manifest["ros"] is None
    assert entries["ros_nodes"]["status"] == "skipped"
    assert manifest["robot"] == "robot" and manifest["fetchsync_version"]
    assert manifest["user"] == snap_env.sshd.user


@pytest.mark.ssh
def test_missing_tool_and_only_and_extra(snap_env, tmp_path):
    result = run_cli(
        "--output",
        str(tmp_path),
        "--only",
        "uname",
        "--only",
        "df",
        "--extra",
        "greet=echo hello-$((6*7))",
        "--extra",
        "nope=fetchsync-no-such-tool-xyz --version",
        "--json",
    )
    assert result.exit_code == 0, _why(result)
    report = json.loads(result.stdout)
    manifest, files = read_archive(Path(report["archive"]))
    entries = by_name(manifest)
    assert list(entries) == ["uname", "df", "greet", "nope"]
    assert files["greet.txt"] == b"hello-42\n"
    assert entries["nope"]["status"] == "missing" and entries["nope"]["exit_code"] == 127
    assert b"not found" in files["nope.stderr.txt"]
    assert report["summary"]["ok"] == 3 and report["summary"]["missing"] == 1


@pytest.mark.ssh
def test_timeout_kills_the_command_on_the_robot(snap_env, tmp_path):
    # A unique argument to find the sleeping process (and its shell) by.
    marker = f"1000.{os.getpid()}{secrets.randbelow(10**6)}"
    config = tmp_path / "slow.json"
    config.write_text(
        json.dumps(
            {
                "defaults": False,
                "collectors": [
                    {"name": "sleeper", "command": f"sleep {marker}; echo never", "timeout": 1},
                    {"name": "quick", "command": "echo done"},
                ],
            }
        )
    )
    result = run_cli("--output", str(tmp_path), "--config", str(config))
    assert result.exit_code == 0, _why(result)
    manifest, files = read_archive(only_archive(tmp_path))
    entries = by_name(manifest)
    assert entries["sleeper"]["status"] == "timeout"
    assert entries["quick"]["status"] == OK and files["quick.txt"] == b"done\n"
    assert "timeout: sleeper" in result.stderr
    left = subprocess.run(
        ["pgrep", "-af", f"sleep {marker}"], check=False, capture_output=True, text=True
    )
    assert left.returncode == 1, f"still running on the robot: {left.stdout}"


# --- ROS (a fake installation) -------------------------------------------------------------------


def fake_ros(root: Path, distro: str, version: int) -> Path:
    """A ``ROS_ROOT/<distro>`` whose setup.bash puts fake ROS tools on PATH."""
    prefix = root / distro
    bin_dir = prefix / "bin"
    bin_dir.mkdir(parents=True)
    (prefix / "setup.bash").write_text(
        f'export PATH="{bin_dir}:$PATH"; export ROS_DISTRO={distro} ROS_VERSION={version}\n'
        'echo "noise from setup" >&2\n'
    )

    def tool(name: str, body: str) -> None:
        path = bin_dir / name
        path.write_text("#!/bin/bash\n" + body)
        path.chmod(0o755)

    if version == 1:
        tool("roscore", "exit 0\n")
        for name in ("rosnode", "rostopic", "rosservice", "rosparam"):
            tool(name, f'echo "{name} $* ($ROS_DISTRO)"\n')
        # rosbag record -q --duration=D -O FILE TOPICS...
        tool(
            "rosbag",
            "shift; out=; topics=; while [ $# -gt 0 ]; do case $1 in -O) out=$2; shift;;"
            ' -*) ;; *) topics="$topics $1";; esac; shift; done\n'
            'echo "bag of$topics" > "$out"\necho "[ INFO] Recording" >&2\n',
        )
    else:
        # ros2 bag record -o DIR TOPICS...: records until SIGINT, like the real one
        tool(
            "ros2",
            'if [ "$1 $2" = "bag record" ]; then shift 3; d=$1; shift; mkdir -p "$d";'
            ' echo "topics: $*" > "$d/metadata.yaml"; trap \'echo closed >> "$d/metadata.yaml";'
            " exit 0' INT; while :; do sleep 0.1; done; fi\n"
            'echo "ros2 $* ($ROS_DISTRO)"\n',
        )
    return prefix


@pytest.fixture
def robot_transport(snap_env) -> Iterator[Any]:
    from fetchsync.link.ssh import SSHTransport

    transport = SSHTransport.connect("robot", connect_timeout=5.0)
    yield transport
    transport.close()


@pytest.mark.ssh
def test_ros1_commands_bag_and_overlay(robot_transport, tmp_path):
    fake_ros(tmp_path / "ros", "noetic", 1)
    ws = tmp_path / "ws"
    (ws / "devel").mkdir(parents=True)
    (ws / "devel" / "setup.bash").write_text("export OVERLAY_MARK=from-the-overlay\n")
    collectors = select_collectors(
        only=["uname", "ros_nodes", "ros_params"],
        extra=[Collector("overlay", "echo $OVERLAY_MARK", kind="ros")],
    )
    snap = take_snapshot(
        robot_transport,
        robot="robot",
        collectors=collectors,
        output=tmp_path,
        ros_root=str(tmp_path / "ros"),
        overlay=str(ws),
        bag_topics=["/diagnostics", "robot_state"],
        bag_duration=1,
    )
    manifest, files = read_archive(snap.archive)
    entries = by_name(manifest)
    assert manifest["ros"] == {
        "version": 1,
        "distro": "noetic",
        "prefix": str(tmp_path / "ros" / "noetic"),
    }
    assert files["ros_nodes.txt"] == b"rosnode list (noetic)\n"
    assert files["ros_params.txt"] == b"rosparam get / (noetic)\n"
    assert "ros_nodes.stderr.txt" not in files  # the setup's noise is not the command's
    assert files["overlay.txt"] == b"from-the-overlay\n"
    assert entries["rosbag"]["status"] == OK
    assert entries["rosbag"]["files"] == ["rosbag/snapshot.bag", "rosbag.stderr.txt"]
    assert files["rosbag/snapshot.bag"] == b"bag of /diagnostics robot_state\n"
    assert entries["ros_nodes"]["kind"] == "ros1"


@pytest.mark.ssh
def test_ros2_commands_and_bag_stopped_by_sigint(robot_transport, tmp_path):
    fake_ros(tmp_path / "ros", "humble", 2)
    collectors = select_collectors(only=["ros_topics"])
    snap = take_snapshot(
        robot_transport,
        robot="robot",
        collectors=collectors,
        output=tmp_path / "out.tar.gz",
        ros_root=str(tmp_path / "ros"),
        bag_topics=["/tf"],
        bag_duration=1,
    )
    assert snap.archive == tmp_path / "out.tar.gz"
    manifest, files = read_archive(snap.archive)
    entries = by_name(manifest)
    assert files["ros_topics.txt"] == b"ros2 topic list -t (humble)\n"
    assert entries["rosbag"]["status"] == OK, entries["rosbag"]
    assert files["rosbag/snapshot_bag/metadata.yaml"] == b"topics: /tf\nclosed\n"


@pytest.mark.ssh
def test_bag_without_ros_is_skipped_and_said(snap_env, tmp_path):
    result = run_cli("--output", str(tmp_path), "--only", "uname", "--bag", "/diagnostics")
    assert result.exit_code == 0, _why(result)
    assert "ROS not found on the robot" in result.stderr
    manifest, _files = read_archive(only_archive(tmp_path))
    assert by_name(manifest)["rosbag"]["status"] == "skipped"
    assert run_cli("--only", "uname", "--bag", "not a topic").exit_code == 2


# --- sudo with a real non-root account ----------------------------------------------------------


@pytest.fixture
def sudo_user(snap_env: SSHHome) -> Iterator[tuple[str, str]]:
    """A throwaway account with a password and a sudoers entry; (name, password)."""
    needed = ("sudo", "useradd", "userdel", "chpasswd")
    if os.geteuid() != 0 or not all(shutil.which(t) for t in needed):
        if os.environ.get("CI"):
            pytest.fail("the sudo tests need root and " + ", ".join(needed))
        pytest.skip("needs root and " + ", ".join(needed))
    name = f"fssnap{os.getpid() % 100000}{secrets.randbelow(1000)}"
    password = "pw-" + secrets.token_urlsafe(12)
    sudoers = Path(f"/etc/sudoers.d/fetchsync-test-{name}")
    subprocess.run(["useradd", "-m", "-s", "/bin/bash", name], check=True, capture_output=True)
    try:
        subprocess.run(
            ["chpasswd"], input=f"{name}:{password}\n", text=True, check=True, capture_output=True
        )
        sudoers.write_text(f"{name} ALL=(ALL:ALL) ALL\n")
        sudoers.chmod(0o440)
        home = Path(os.path.expanduser(f"~{name}"))
        ssh_dir = home / ".ssh"
        ssh_dir.mkdir(mode=0o700)
        shutil.copyfile(snap_env.identity.with_suffix(".pub"), ssh_dir / "authorized_keys")
        shutil.chown(ssh_dir, name, name)
        shutil.chown(ssh_dir / "authorized_keys", name, name)
        yield name, password
    finally:
        sudoers.unlink(missing_ok=True)
        subprocess.run(["userdel", "-r", "-f", name], check=False, capture_output=True)


def sudo_config(tmp_path: Path) -> Path:
    config = tmp_path / "sudo.json"
    config.write_text(
        json.dumps(
            {
                "defaults": False,
                "collectors": [
                    {"name": "root_id", "command": "id -u", "needs_sudo": True},
                    {"name": "slow_root_id", "command": "sleep 2; id -u", "needs_sudo": True},
                    {"name": "my_id", "command": "id -un"},
                ],
            }
        )
    )
    return config


@pytest.mark.ssh
def test_sudo_password_goes_on_stdin_never_in_a_command_line(sudo_user, tmp_path):
    name, password = sudo_user
    seen: list[str] = []
    stop = threading.Event()

    def watch() -> None:
        while not stop.is_set():
            out = subprocess.run(
                ["ps", "-eo", "args"], check=False, capture_output=True, text=True
            ).stdout
            seen.extend(line for line in out.splitlines() if password in line)
            stop.wait(0.02)

    watcher = threading.Thread(target=watch, daemon=True)
    watcher.start()
    try:
        result = run_cli(
            "--user",
            name,
            "--sudo",
            "--output",
            str(tmp_path),
            "--json",
            "--config",
            str(sudo_config(tmp_path)),
            env={"FETCHSYNC_SUDO_PASSWORD": password},
        )
    finally:
        stop.set()
        watcher.join()
    assert result.exit_code == 0, _why(result)
    assert seen == []
    manifest, files = read_archive(only_archive(tmp_path))
    entries = by_name(manifest)
    assert manifest["sudo"] == "password" and manifest["user"] == name
    assert files["root_id.txt"] == b"0\n" and entries["root_id"]["sudo"] is True
    assert files["slow_root_id.txt"] == b"0\n"
    assert files["my_id.txt"] == f"{name}\n".encode() and entries["my_id"]["sudo"] is False
    assert all(password.encode() not in data for data in files.values())
    assert password not in result.output


@pytest.mark.ssh
def test_sudo_wrong_or_no_password(sudo_user, tmp_path):
    name, password = sudo_user
    config = str(sudo_config(tmp_path))
    result = run_cli(
        "--user",
        name,
        "--output",
        str(tmp_path),
        "--config",
        config,
        env={"FETCHSYNC_SUDO_PASSWORD": password + "x"},
    )
    assert result.exit_code == 2 and "refused the password" in result.stderr
    assert password not in result.output
    assert list(tmp_path.glob("snapshot-*")) == []
    # no password and no terminal: --sudo refuses, the default runs them without sudo
    result = run_cli("--user", name, "--sudo", "--output", str(tmp_path), "--config", config)
    assert result.exit_code == 2 and "FETCHSYNC_SUDO_PASSWORD" in result.stderr
    result = run_cli("--user", name, "--output", str(tmp_path), "--config", config)
    assert result.exit_code == 0, _why(result)
    assert "without sudo" in result.stderr
    _manifest, files = read_archive(only_archive(tmp_path))
    assert files["root_id.txt"] != b"0\n"


# --- fetch_tools' collection and ROS 2's, with fakes on a robot user's PATH ----------------------


def _fake_tools(user: str, tools: dict[str, str]) -> Path:
    """Put fake executables in ~USER/fakebin, first on the PATH of the user's SSH commands
    (bash reads ~/.bashrc for them), as a robot's own tools would be."""
    home = Path(os.path.expanduser(f"~{user}"))
    bin_dir = home / "fakebin"
    bin_dir.mkdir(exist_ok=True)
    for name, body in tools.items():
        (bin_dir / name).write_text("#!/bin/bash\n" + body)
        (bin_dir / name).chmod(0o755)
    (home / ".bashrc").write_text(f'export PATH="{bin_dir}:$PATH"\n')
    for path in (bin_dir, *bin_dir.iterdir(), home / ".bashrc"):
        shutil.chown(path, user, user)
    return home


def _read_zip(path: Path) -> tuple[dict[str, Any], dict[str, bytes]]:
    import zipfile

    with zipfile.ZipFile(path) as z:
        names = z.namelist()
        assert len({n.split("/", 1)[0] for n in names}) == 1, names
        files = {n.split("/", 1)[1]: z.read(n) for n in names}
    return json.loads(files["manifest.json"]), files


def _why(result: Any) -> str:
    """The command's output and, when it raised, the whole chain: click prints only
    ``Aborted!`` for an EOFError or KeyboardInterrupt, which says nothing of where."""
    if (
        result.exc_info is None
        or isinstance(result.exception, SystemExit)
        and not (result.exception.__context__ or result.exception.__cause__)
    ):
        return result.output
    return result.output + "".join(traceback.format_exception(*result.exc_info))


FAKE_ROSBAG = (
    '[ "$1" = record ] || exit 2; out=; args="$*"; while [ $# -gt 0 ]; do '
    'case $1 in -O) out=$2; shift;; esac; shift; done; echo "$args" > "$out"\n'
)


@pytest.mark.ssh
def test_debug_snapshot_is_fetch_tools_collection_in_a_zip(sudo_user, tmp_path):
    name, password = sudo_user
    _fake_tools(name, {"read_board": 'echo "board $1"\n', "rosbag": FAKE_ROSBAG})
    result = CliRunner().invoke(
        cli,
        ["debug-snapshot", "--user", name, "--output", str(tmp_path)],
        env={"FETCHSYNC_SUDO_PASSWORD": password},
    )
    assert result.exit_code == 0, _why(result)
    (archive,) = tmp_path.glob("snapshot-robot-*.zip")
    manifest, files = _read_zip(archive)
    entries = by_name(manifest)
    assert manifest["user"] == name and manifest["ros"]["version"] == 1
    # where the answer comes from and goes, first, on stderr
    assert result.stderr.splitlines()[0] == f"snapshot {name}@robot \u2192 {tmp_path}"
    assert manifest["sudo"] == "password" and entries["dmesg"]["sudo"] is True
    # the five board queries, through the robot's read_board
    for entry, address in (
        ("charger", "0x3f"),
        ("mainboard", "0x00"),
        ("wheel_left", "0x11"),
        ("wheel_right", "0x12"),
        ("gripper", "0x80"),
    ):
        assert files[f"read_board_{entry}.txt"] == f"board {address}\n".encode()
    # fetch_tools' 10 s bag of its four topics
    assert entries["rosbag"]["status"] == OK
    assert files["rosbag/snapshot.bag"] == (
        b"record -q --duration=10 -O snapshot.bag /robot_state "
        b"/diagnostics /diagnostics_agg /battery_state\n"
    )
    assert b"fakebin" in files["env.txt"] and b"MemTotal" in files["meminfo.txt"]
    # what this machine lacks is skipped, each with a note saying what was absent
    for item, absent in (
        ("robot_log", "/var/log/ros/robot.log"),
        ("robot.service_status", "/lib/systemd/system/robot.service"),
        ("roscore.service", "/lib/systemd/system/roscore.service"),
        ("ps4joy.service_status", "/lib/systemd/system/ps4joy.service"),
    ):
        assert entries[item]["status"] == "skipped", entries[item]
        assert entries[item]["error"] == f"not on the robot: {absent}"
        assert f"{item}.txt" not in files and f"{item}.stderr.txt" not in files
        assert f"skipped: {item} (not on the robot: {absent})" in result.stderr
    assert entries["roswtf"]["status"] == "missing"
    assert entries["roswtf"]["error"] == "not installed on the robot"
    assert password.encode() not in b"".join(files.values())


@pytest.mark.ssh
def test_debug_snapshot_logs_in_as_fetch_like_fetch_tools(sudo_user, tmp_path):
    name, _password = sudo_user
    # FETCH_USER is the developer's account; fetch_tools' debug-snapshot used `fetch` anyway
    result = CliRunner().invoke(
        cli,
        ["debug-snapshot", "--output", str(tmp_path)],
        env={"FETCH_USER": name, "FETCHSYNC_USER": name},
    )
    assert result.exit_code == 3
    assert "permission denied for fetch@robot" in result.stderr, result.stderr


FAKE_ROS2 = """case "$1 $2" in
  "doctor --report") echo "doctor report: all good";;
  "node list") echo /talker;;
  "topic list") echo "/chatter [std_msgs/msg/String]";;
  "service list") echo /talker/describe_parameters;;
  "param list") echo /talker:;;
  *) echo "ros2 $*"; exit 1;;
esac
"""


@pytest.mark.ssh
def test_generic_profile_collects_ros2_counterparts(sudo_user, tmp_path):
    name, _password = sudo_user
    home = _fake_tools(name, {"ros2": FAKE_ROS2})
    only = [
        "--only",
        "uname",
        "--only",
        "ros_doctor",
        "--only",
        "ros_nodes",
        "--only",
        "ros_topics",
        "--only",
        "ros_log",
    ]
    # no ~/.ros/log yet: skipped, said so
    result = run_cli("--user", name, "--output", str(tmp_path / "one.tar.gz"), *only)
    assert result.exit_code == 0, _why(result)
    manifest, files = read_archive(tmp_path / "one.tar.gz")
    entries = by_name(manifest)
    assert manifest["ros"]["version"] == 2
    assert files["ros_doctor.txt"] == b"doctor report: all good\n"
    assert files["ros_nodes.txt"] == b"/talker\n"
    assert files["ros_topics.txt"] == b"/chatter [std_msgs/msg/String]\n"
    assert entries["ros_log"]["status"] == "skipped"
    assert entries["ros_log"]["error"] == "not on the robot: ~/.ros/log"

    # the last day of logs, in ros_log/, into a .zip this time
    log_dir = home / ".ros" / "log"
    (log_dir / "2026-11-26-10-00-00-123").mkdir(parents=True)
    (log_dir / "python3_1234_1700000000000.log").write_text("recent\n")
    (log_dir / "2026-11-26-10-00-00-123" / "launch.log").write_text("launch\n")
    old = log_dir / "python3_1_1.log"
    old.write_text("old\n")
    os.utime(old, (1.0e9, 1.0e9))
    subprocess.run(["chown", "-R", f"{name}:{name}", str(home / ".ros")], check=True)
    result = run_cli("--user", name, "--output", str(tmp_path), "--zip", *only)
    assert result.exit_code == 0, _why(result)
    (archive,) = tmp_path.glob("snapshot-robot-*.zip")
    manifest, files = _read_zip(archive)
    assert by_name(manifest)["ros_log"]["status"] == OK
    assert files["ros_log/log/python3_1234_1700000000000.log"] == b"recent\n"
    assert files["ros_log/log/2026-11-26-10-00-00-123/launch.log"] == b"launch\n"
    assert "ros_log/log/python3_1_1.log" not in files
