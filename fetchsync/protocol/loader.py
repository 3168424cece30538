"""Delivery of the robot-side endpoint over the connection itself.

The client runs a short fixed stub with ``python3 -S -c`` on the robot (~1.3 KB
of command line at every endpoint start, where the whole loader took 4.3 KB).
The stub refuses a Python older than 3.6 with a message that says so (the
endpoint itself would fail with a SyntaxError that says nothing useful), then
runs the loader from the cache: ``loader-HASH.py`` in the private cache
directory (opened without following a symlink, the user's and mode 0700, the
file the user's, regular and writable by no one else), only if its SHA-256 is
the one on the command line; else it says ``NEED_LOADER``, reads the loader
from stdin, checks its hash and runs it, and the loader caches itself once it
has checked the directory as below. Both take SHA-256 from the interpreter's own
``_sha256`` (``_sha2`` from 3.12; hashlib only where neither is built in): importing
hashlib loads OpenSSL's ``_hashlib``, 6.9 ms of the ~50 ms from the endpoint's exec to
its hello on the bench's robot (``python3 -X importtime``, 3.11), and nothing else the
endpoint imports needs it (hashing.py takes ``_blake2`` the same way). The loader looks
for the endpoint (a zip of ``fetchsync.protocol``) in the user's cache
directory under its content hash; when it is missing it says ``NEED`` and
reads exactly that many bytes from stdin, checks their hash and caches them.
A loader the stub had to receive reads the endpoint right after itself without
asking (the client sends both on ``NEED_LOADER``: a robot without this loader
lacks this endpoint too, as both change with fetchsync's version), checked the
same way: one round trip for a new robot or a new version, not two.
It runs the endpoint from a directory beside the zip, extracted and compiled
once per Python version (a zip's modules are compiled again at every start:
~50 ms of each connection), synced before it is renamed into place. Starts at
once (two laptops, two pushes to a robot new to this version) extract one at a time
under a lock on the cache directory, and each looks again once it holds it: an
extracted tree another start runs from (importing from it lazily) is never moved
away; a start whose lock another holds over 5 s runs from the checked zip.

The cache is the robot user's alone: its directory is made ``0700``, opened
without following a symlink and checked to be owned by the user (another
user's directory is refused with one line; one that was open to others has its
endpoints removed before it is closed to them), its files are written ``0600``
(the extracted tree under umask ``077``) whatever the login's umask, the zip is
checked against its SHA-256 at every start (not its size), and the extracted
tree is used only while everything in it is the user's and writable by no one
else; it is extracted from the verified bytes, not from the file again.
Nothing is installed with root and nothing is downloaded by the robot.
"""

import hashlib
import os
from typing import Callable, Tuple

from fetchsync.protocol.errors import ProtocolError

NEED = b"FSYNC-NEED\n"
NEED_LOADER = b"FSYNC-NEED-LOADER\n"

# The command line of every endpoint start: '' (``-c``'s working directory, the robot
# user's home) off the import path before anything is imported (a ~/queue.py or
# ~/typing.py broke every start, or ran as the endpoint), the version check, then the loader from
# the cache when the private cache directory holds it under its hash, else from the
# client (it caches itself). Every byte of it crosses the link at every start (a push
# through the master pays its spare's), and every user on the robot can read it in ps.
STUB = r"""
import sys
sys.path[:] = [p for p in sys.path if p]
import os
try:from _sha256 import sha256
except ImportError:
 try:from _sha2 import sha256
 except ImportError:from hashlib import sha256
if sys.version_info < (3, 6):
    sys.exit("python %d.%d.%d on the robot is too old, fetchsync needs python3 >= 3.6: install one (apt install python3) and set FETCHSYNC_REMOTE_PYTHON to it" % tuple(sys.version_info[:3]))
h, n, u = sys.argv[1], int(sys.argv[2]), os.getuid()
def cached():
    d = os.open(os.path.join(os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache"), "fetchsync"), os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW)
    try:
        s = os.fstat(d)
        if s.st_uid != u or s.st_mode & 0o077:
            return None
        f = os.fdopen(os.open("loader-" + h[:32] + ".py", os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK, dir_fd=d), "rb")
    finally:
        os.close(d)
    with f:
        s = os.fstat(f.fileno())
        return f.read(n + 1) if s.st_uid == u and s.st_mode & 0o170022 == 0o100000 else None
try:
    b = cached()
except OSError:
    b = None
g = {"__name__": "__main__", "__builtins__": __builtins__, "NEW": None, "LH": h}
if b is None or sha256(b).hexdigest() != h:
    sys.stdout.buffer.write(b"FSYNC-NEED-LOADER\n")
    sys.stdout.buffer.flush()
    b = g["NEW"] = sys.stdin.buffer.read(n)
    if sha256(b).hexdigest() != h:
        sys.exit("fetchsync: the loader was damaged in transit")
del sys.argv[1:3]
exec(compile(b, "fetchsync-loader", "exec"), g)
""".strip()

LOADER = r"""
import sys
sys.path[:] = [p for p in sys.path if p]
import os
if sys.version_info < (3, 6):
    sys.exit("python %d.%d.%d on the robot is too old, fetchsync needs python3 >= 3.6: install one (apt install python3) and set FETCHSYNC_REMOTE_PYTHON to it" % tuple(sys.version_info[:3]))
if sys.flags.no_site:
    import site
    v = os.path.dirname(os.path.dirname(sys.executable))
    v = [os.path.join(v, "lib", "python%d.%d" % sys.version_info[:2], "site-packages")] if os.path.isfile(os.path.join(v, "pyvenv.cfg")) else []
    sys.path.extend(d for d in ([site.getusersitepackages()] if not sys.flags.no_user_site and not v else []) + v + site.getsitepackages() if d not in sys.path and os.path.isdir(d))
h, n = sys.argv[1], int(sys.argv[2])
import stat
try:
    from _sha256 import sha256
except ImportError:
    try:
        from _sha2 import sha256
    except ImportError:
        from hashlib import sha256
u = os.getuid()
def bad(s):
    sys.exit("fetchsync: %s: refusing to use the endpoint cache; remove it (fetchsync recreates it)" % s)
def mine(p, dirs):
    s = os.lstat(p)
    return s.st_uid == u and not s.st_mode & 0o022 and (stat.S_ISDIR(s.st_mode) if dirs else stat.S_ISREG(s.st_mode))
c = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
d = os.path.join(c, "fetchsync")
try:
    os.makedirs(c, exist_ok=True)
    os.mkdir(d, 0o700)
except FileExistsError:
    pass
try:
    fd = os.open(d, os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW)
except OSError as e:
    bad("%s is a symlink or not a directory (%s)" % (d, e.strerror))
s = os.fstat(fd)
if s.st_uid != u:
    bad("%s belongs to another user" % d)
def lock():
    # one start at a time changes what is cached: another may be extracting, or running
    # from what it extracted; one that holds the lock over 5 s (stopped, a hung disk) is
    # not waited for (the caller then changes nothing)
    import fcntl, time
    for i in range(100):
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            return True
        except BlockingIOError:
            time.sleep(0.05)
        except OSError:
            return True  # no locks here (some NFS): as without them
    return False
def unlock():
    import fcntl
    try:
        fcntl.flock(fd, fcntl.LOCK_UN)
    except OSError:
        pass
if s.st_mode & 0o077:
    lock()  # else without it, as before: this cache is not to be used open
    try:
        # once open to others (a cache made under umask 000): what it holds may be theirs
        if os.fstat(fd).st_mode & 0o077:
            for e in os.listdir(fd):
                if e.startswith("endpoint-") and not e.endswith(".note"):
                    t = os.path.join(d, ".stale-%d-%s" % (os.getpid(), e))
                    os.rename(os.path.join(d, e), t)
                    import shutil
                    shutil.rmtree(t, ignore_errors=True)
                    if os.path.lexists(t):
                        os.unlink(t)
            os.fchmod(fd, 0o700)
    finally:
        unlock()
if os.path.isdir("/proc/self/fd/%d" % fd):
    d = "/proc/self/fd/%d" % fd  # this very directory, whatever is renamed meanwhile
def put(p, b):
    t = p + ".%d.tmp" % os.getpid()
    f = os.open(t, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_NOFOLLOW, 0o600)
    try:  # a full disk leaves no partial file
        os.fchmod(f, 0o600)
        with open(f, "wb") as f:
            f.write(b)
            f.flush()
            os.fsync(f.fileno())
        os.replace(t, p)
    except BaseException:
        os.unlink(t)
        raise
if globals().get("NEW"):  # the stub received this loader: cache it for the next starts
    try:
        put(os.path.join(d, "loader-" + LH[:32] + ".py"), NEW)
    except OSError:
        pass
p = os.path.join(d, "endpoint-" + h[:32] + ".pyz")
b = None
try:
    if mine(p, False):
        with open(p, "rb") as f:
            b = f.read(n + 1)
        if sha256(b).hexdigest() != h:
            b = None
except OSError:
    b = None
if b is None or globals().get("NEW"):
    # a client that had to send this loader sent the endpoint right after it, unasked
    if not globals().get("NEW"):
        o = sys.stdout.buffer
        o.write(b"FSYNC-NEED\n")
        o.flush()
    e = sys.stdin.buffer.read(n)
    if sha256(e).hexdigest() != h:
        sys.exit("fetchsync: the endpoint was damaged in transit")
    if b is None:
        put(p, e)
    b = e
x = p[:-4] + "-" + str(sys.implementation.cache_tag)
def whole(x):
    if not os.path.isdir(x) or not mine(x, True):
        return False
    for r, ds, fs in os.walk(x):
        for e in ds + fs:
            if not mine(os.path.join(r, e), e in ds):
                return False
    return True
def extract():
    import shutil
    # what an extraction killed midway left (one extracts at a time: none is under way)
    for e in os.listdir(fd):
        if e.startswith("endpoint-") and e.endswith((".tmp", ".old")) and mine(os.path.join(d, e), True):
            shutil.rmtree(os.path.join(d, e), ignore_errors=True)
    if os.path.lexists(x):
        t = x + ".%d.old" % os.getpid()
        os.rename(x, t)
        shutil.rmtree(t, ignore_errors=True)
    t = x + ".%d.tmp" % os.getpid()
    m = os.umask(0o077)
    try:
        import zipfile, py_compile, io
        with zipfile.ZipFile(io.BytesIO(b)) as z:
            z.extractall(t)
        for r, _, fs in os.walk(t):
            for f in fs:
                if f.endswith(".py"):
                    py_compile.compile(os.path.join(r, f), doraise=True, **({"invalidation_mode": py_compile.PycInvalidationMode.UNCHECKED_HASH} if hasattr(py_compile, "PycInvalidationMode") else {}))
        for r, _, fs in os.walk(t, topdown=False):
            for f in fs + ["."]:
                fd2 = os.open(os.path.join(r, f), os.O_RDONLY)
                os.fsync(fd2)
                os.close(fd2)
        try:
            os.rename(t, x)
        except OSError:
            shutil.rmtree(t, ignore_errors=True)
        os.fsync(fd)
    except Exception:
        shutil.rmtree(t, ignore_errors=True)
    finally:
        os.umask(m)
if not whole(x) and lock():
    try:
        if not whole(x):  # another start may have extracted it meanwhile, and run from it
            extract()
    finally:
        unlock()
sys.dont_write_bytecode = True
sys.path.insert(0, x if whole(x) else p)
from fetchsync.protocol.server import main
main()
""".strip()

LOADER_BYTES = LOADER.encode()  # sent when the stub says NEED_LOADER
_LOADER_DIGEST = hashlib.sha256(LOADER_BYTES).hexdigest()

_PACKAGE_INIT = b'"""fetchsync robot-side endpoint (the protocol package only)."""\n'
_cache = None  # type: Tuple[bytes, str] | None


def endpoint_archive() -> "Tuple[bytes, str]":
    """The endpoint as a deterministic zip, and its sha256 (hex)."""
    global _cache
    if _cache is not None:
        return _cache
    import hashlib
    import io
    import zipfile

    here = os.path.dirname(os.path.abspath(__file__))
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:

        def add(name: str, data: bytes) -> None:
            info = zipfile.ZipInfo(name, date_time=(2020, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_DEFLATED
            info.external_attr = 0o644 << 16
            zf.writestr(info, data)

        add("fetchsync/__init__.py", _PACKAGE_INIT)
        for name in sorted(os.listdir(here)):
            if name.endswith(".py"):
                with open(os.path.join(here, name), "rb") as fh:
                    add("fetchsync/protocol/" + name, fh.read())
    data = buf.getvalue()
    _cache = (data, hashlib.sha256(data).hexdigest())
    return _cache


def cache_dir() -> str:
    """fetchsync's cache directory on this machine (the loader's too, on the robot)."""
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "fetchsync")


def write_cache_file(path: str, text: str) -> None:
    """Replace the small cache file ``path`` with ``text`` at once (a reader sees the old
    or the new one); only a cache, so a failure passes."""
    try:
        os.makedirs(os.path.dirname(path), mode=0o700, exist_ok=True)
        tmp = "%s.%d.tmp" % (path, os.getpid())
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_NOFOLLOW, 0o600)
        with open(fd, "w", encoding="utf-8") as fh:
            fh.write(text)
        os.replace(tmp, path)
    except OSError:
        pass


def _sources_stamp(here: str) -> str:
    """A key that changes whenever a source of the endpoint does (name, size, mtime)."""
    import hashlib

    stats = []
    for entry in os.scandir(here):
        if entry.name.endswith(".py"):
            st = entry.stat()
            stats.append((entry.name, st.st_size, st.st_mtime_ns))
    return hashlib.sha256(repr(sorted(stats)).encode()).hexdigest()[:32]


def endpoint_digest() -> "Tuple[str, int]":
    """The archive's sha256 and length, without building it when a local note has them.

    Building the zip (and importing zipfile) costs a new process ~10 ms, and
    a call through the connection master only needs the command line.
    """
    if _cache is not None:
        return _cache[1], len(_cache[0])
    here = os.path.dirname(os.path.abspath(__file__))
    note = os.path.join(cache_dir(), "endpoint-%s.note" % _sources_stamp(here))
    try:
        with open(note, "r", encoding="ascii") as fh:
            digest, length = fh.read().split()
        if len(digest) == 64 and int(length) > 0:
            return digest, int(length)
    except (OSError, ValueError):
        pass
    data, digest = endpoint_archive()
    write_cache_file(note, "%s %d\n" % (digest, len(data)))
    return digest, len(data)


def loader_spec(python: str = "python3") -> "Tuple[str, Callable[[], bytes]]":
    """The remote command line that starts the endpoint, and how to get the archive on NEED."""
    digest, length = endpoint_digest()
    # -S: no .pth hooks nor sitecustomize run before the endpoint (a robot's
    # site-packages can hold dozens: 40 ms of every start here, and anything they
    # print would go down the protocol's stream); the loader puts the site
    # directories on the path itself, for the optional xxhash
    import shlex

    cmd = "%s -S -c %s %s %d %s %d" % (
        python,
        shlex.quote(STUB),
        _LOADER_DIGEST,
        len(LOADER_BYTES),
        digest,
        length,
    )

    def archive() -> bytes:
        data, actual = endpoint_archive()
        if actual != digest:  # the note is wrong (a source rewritten within its mtime?)
            for name in os.listdir(cache_dir()):
                if name.startswith("endpoint-") and name.endswith(".note"):
                    try:
                        os.unlink(os.path.join(cache_dir(), name))
                    except OSError:
                        pass
            raise ProtocolError(
                "fetchsync's endpoint changed while it was starting; run the command again"
            )
        return data

    return cmd, archive


def loader_command(python: str = "python3") -> "Tuple[str, bytes]":
    """The loader's own command line (no stub: it asks only for the archive, on NEED),
    and the archive: for tests and tools that drive a loader by hand."""
    import shlex

    digest, length = endpoint_digest()
    data, _ = endpoint_archive()
    return "%s -S -c %s %s %d" % (python, shlex.quote(LOADER), digest, length), data
