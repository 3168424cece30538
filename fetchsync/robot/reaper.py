"""Run one command on the robot so that it ends when the SSH channel ends.

This file runs on the robot, by itself: ``fetchsync.chores.remote`` sends its source
as ``python3 -c SOURCE MODE COMMAND...``. It must therefore run on Python 3.8
with the standard library only and import nothing from fetchsync (``-c``
runs it as ``__main__``; importing it does nothing).

Why it exists: without a PTY, sshd neither forwards a signal nor hangs up the
command when the client goes away (Ctrl-C, a killed laptop process, a lost
link); ``sleep 300`` and ``roslaunch`` would keep running. So the command runs
in its own process group, and this process watches the channel:

- ``pipe`` mode: the command runs in a new session. When sshd closes the other
  end of stdout or stderr (the channel closed or the connection died), the
  group gets SIGINT, the signal Ctrl-C sends and ROS nodes shut down cleanly
  on; once the command has ended (or after a grace period) what is left gets
  SIGTERM, then SIGKILL, until none is left.
- ``tty`` mode: the command runs in its own process group made the terminal's
  foreground group, so ``^C`` typed on the laptop reaches it as SIGINT through
  the PTY; a hang-up of the terminal stops the group the same way.

A SIGHUP, SIGINT or SIGTERM sent to this process is passed on to the group.
The exit status is the command's, or 128 + N when signal N killed it.
"""

import os
import select
import signal
import sys
import time

_GRACE = ((signal.SIGINT, 10.0), (signal.SIGTERM, 5.0), (signal.SIGKILL, 5.0))
_GONE = select.POLLERR | select.POLLHUP | select.POLLNVAL
_PASSED_ON = (signal.SIGHUP, signal.SIGINT, signal.SIGTERM)


def _status(wait_status):
    if os.WIFSIGNALED(wait_status):
        return 128 + os.WTERMSIG(wait_status)
    return os.WEXITSTATUS(wait_status)


def _start(argv, tty):
    pid = os.fork()
    if pid:
        if tty:
            # Both sides set the group: whichever runs first wins the race.
            try:
                os.setpgid(pid, pid)
                os.tcsetpgrp(0, pid)
            except OSError:
                pass
        return pid
    try:
        if tty:
            os.setpgid(0, 0)
            try:
                os.tcsetpgrp(0, os.getpgrp())
            except OSError:
                pass
        else:
            os.setsid()
        # Python ignores these; the command must get the defaults back.
        for sig in (signal.SIGPIPE, signal.SIGXFSZ, signal.SIGTTOU, signal.SIGCHLD) + _PASSED_ON:
            signal.signal(sig, signal.SIG_DFL)
        os.execvp(argv[0], argv)
    except OSError as exc:
        os.write(2, f"fetchsync: cannot run {argv[0]}: {exc.strerror}\n".encode())
    os._exit(127)


def _group_alive(pgid):
    try:
        os.killpg(pgid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _stop_group(pid):
    """Stop the command's group: SIGINT, SIGTERM once the command ended or after a grace, SIGKILL.

    The command gets SIGINT and time to shut down as after Ctrl-C (roslaunch
    stops its nodes); what is left then, such as the background jobs of a
    non-interactive shell, which ignore SIGINT, gets SIGTERM and SIGKILL.
    """
    status = None
    for sig, grace in _GRACE:
        try:
            os.killpg(pid, sig)
            if sig == signal.SIGTERM:
                os.killpg(pid, signal.SIGCONT)  # a stopped process must run to die
        except ProcessLookupError:
            break
        deadline = time.monotonic() + grace
        while time.monotonic() < deadline:
            if status is None:
                done, wait_status = os.waitpid(pid, os.WNOHANG)
                if done:
                    status = _status(wait_status)
            if status is not None and (sig == signal.SIGINT or not _group_alive(pid)):
                break
            time.sleep(0.05)
        if status is not None and not _group_alive(pid):
            break
    return status


def main(argv):
    mode, command = argv[0], argv[1:]
    tty = mode == "tty"
    wake_r, wake_w = os.pipe()
    os.set_blocking(wake_w, False)
    signal.set_wakeup_fd(wake_w)
    caught = []

    def note(signum, _frame):
        caught.append(signum)

    signal.signal(signal.SIGCHLD, note)
    for sig in _PASSED_ON:
        signal.signal(sig, note)
    if tty:
        # tcsetpgrp from what becomes a background group would stop us otherwise.
        signal.signal(signal.SIGTTOU, signal.SIG_IGN)
    pid = _start(command, tty)

    poller = select.poll()
    poller.register(wake_r, select.POLLIN)
    for fd in (0,) if tty else (1, 2):
        try:
            os.fstat(fd)
        except OSError:
            continue
        poller.register(fd, 0)  # errors and hang-ups are reported whatever the mask
    status = None
    while status is None:
        try:
            events = poller.poll()
        except InterruptedError:
            events = []
        done, wait_status = os.waitpid(pid, os.WNOHANG)
        if done:
            status = _status(wait_status)
            break
        hung_up = any(fd != wake_r and flags & _GONE for fd, flags in events)
        if any(fd == wake_r for fd, _ in events):
            try:
                os.read(wake_r, 512)
            except BlockingIOError:
                pass
        passed = [sig for sig in caught if sig in _PASSED_ON]
        del caught[:]
        if hung_up or signal.SIGHUP in passed:
            # Nobody is left to read the status; the group just must not outlive us.
            status = _stop_group(pid)
            return 128 + signal.SIGHUP if status is None else status
        for sig in passed:
            try:
                os.killpg(pid, sig)
            except ProcessLookupError:
                pass
    return status


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
