"""The adversarial replay's machinery: running the tested command in a session of its own, checking its
promises, building the fixtures, and the registry of cases (benchmarks/adversarial_replay.py runs them)."""
from __future__ import annotations

import contextlib
import hashlib
import itertools
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
import zlib
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

ESC = "\x1b"
#: What a failed or finished run must not leave: temporary ``.NAME.*.part``, ``.NAME.old-PID``, ``.OUT.partial``.
STRAY = re.compile(r"^\..+\.(part|old-\d+)$|\.partial$")

# ----------------------------------------------------------------------------- running the command
@dataclass
class Run:
    """One finished command: exit code (negative: killed by that signal), output, time, processes left."""

    argv: list[str]
    code: int
    out: str
    err: str
    seconds: float
    orphans: list[int] = field(default_factory=list)


def session_processes(sid: int) -> list[int]:
    """Live (not zombie) processes of session ``sid`` (the command's own session: its workers stay in it)."""
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[3]) == sid and fields[0] != "Z":
            found.append(int(entry.name))
    return found


def wait_orphans(sid: int, seconds: float = 5.0) -> list[int]:
    """Processes of session ``sid`` still alive after ``seconds``; they are then killed, and returned."""
    deadline = time.monotonic() + seconds
    while (left := session_processes(sid)) and time.monotonic() < deadline:
        time.sleep(0.1)
    for pid in left:
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.kill(pid, signal.SIGKILL)
    return left


class Runner:
    """Runs the tested command from a fixed folder, each run in a new session."""

    def __init__(self, forensics: str, cwd: Path, workers: int, logs: Path):
        self.forensics, self.cwd, self.workers, self.logs = forensics, cwd, workers, logs
        self.env = {k: v for k, v in os.environ.items() if k not in ("FORENSICS_DEBUG", "PYTHONPATH")}
        self.env["NO_COLOR"] = "1"
        self.last_err: dict[int, str] = {}  # per thread: stderr of its last run, shown for a failing case
        self._numbers = itertools.count(1)  # next() is atomic: cases run on threads

    def start(self, *argv, env: dict | None = None, umask: int | None = None, fsize: int | None = None,
              ) -> tuple[subprocess.Popen, Path]:
        """Start ``forensics argv`` in the background (output to files, which survivors cannot block)."""
        log = self.logs / f"run{next(self._numbers):04d}"
        log.mkdir(parents=True)

        def before() -> None:
            if umask is not None:
                os.umask(umask)
            if fsize is not None:  # `ulimit -f`: writes past it fail with EFBIG (Python ignores SIGXFSZ)
                import resource
                signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
                resource.setrlimit(resource.RLIMIT_FSIZE, (fsize, fsize))

        with open(log / "out", "wb") as out, open(log / "err", "wb") as err:
            proc = subprocess.Popen([self.forensics, *map(str, argv)], cwd=self.cwd, stdout=out, stderr=err,
                                    stdin=subprocess.DEVNULL, env={**self.env, **(env or {})},
                                    start_new_session=True, preexec_fn=before)
        proc.argv = [str(a) for a in argv]  # type: ignore[attr-defined]
        return proc, log

    def finish(self, proc: subprocess.Popen, log: Path, started: float, timeout: float = 120) -> Run:
        try:
            code = proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            code = proc.wait()
            (log / "err").write_bytes((log / "err").read_bytes() + f"\n[replay: timed out after {timeout} s]\n".encode())
        seconds = time.monotonic() - started
        orphans = wait_orphans(proc.pid)
        read = lambda name: (log / name).read_bytes().decode("utf-8", "replace")  # noqa: E731
        self.last_err[threading.get_ident()] = read("err")[-1500:]
        return Run(proc.argv, code, read("out"), read("err"), seconds, orphans)  # type: ignore[attr-defined]

    def __call__(self, *argv, timeout: float = 120, **options) -> Run:
        started = time.monotonic()
        proc, log = self.start(*argv, **options)
        return self.finish(proc, log, started, timeout)


# ----------------------------------------------------------------------------- checking promises
def strict_json(text: str) -> object:
    """Parse standard JSON only (NaN, Infinity are not JSON)."""
    def refuse(token: str) -> None:
        raise ValueError(f"non-standard JSON token {token}")
    return json.loads(text, parse_constant=refuse)


def check(run: Run, code: int, *needles: str, json_out: bool = False, quiet_err: bool = False) -> list[str]:
    """What is wrong with ``run`` against the promise: exit ``code``; on failure exactly one line on stderr
    (``forensics: …``) holding every needle; never a traceback or a raw control character; no survivors."""
    problems = []
    if run.code != code:
        problems.append(f"exit {run.code}, not {code}")
    err_lines = error_lines(run.err)
    if "Traceback" in run.err:
        problems.append("traceback on stderr")
    if code != 0:
        if len(err_lines) != 1 or not err_lines[0].startswith("forensics"):
            problems.append(f"{len(err_lines)} lines on stderr")
    elif quiet_err and err_lines:
        problems.append(f"{len(err_lines)} lines on stderr")
    for needle in needles:
        if needle not in run.err:
            problems.append(f"stderr lacks {needle!r}")
    if ESC in run.out or ESC in run.err:
        problems.append("raw ESC on the terminal")
    if json_out:
        try:
            strict_json(run.out)
        except ValueError as exc:
            problems.append(f"stdout is not standard JSON ({exc})")
    if run.orphans:
        problems.append(f"{len(run.orphans)} process(es) survived the command")
    return problems


def error_lines(err: str) -> list[str]:
    """stderr without warnings (``warning: …``, one line each) and without argparse's usage synopsis, which it
    prints before its one error line (``usage: …`` and its indented continuation lines)."""
    lines = [line for line in err.strip().splitlines() if not line.startswith("warning: ")]
    if lines and lines[0].startswith("usage: "):
        lines = [line for line in lines[1:] if not line.startswith(" ")]
    return lines


def observed(run: Run) -> str:
    first = (run.err.strip().splitlines() or [""])[-1]
    return f"exit {run.code}" + (f": {first[:110]}" if first else "")


def tree_hashes(root: Path) -> dict[str, str]:
    """Every path under ``root`` (hidden ones included) with the SHA-256 of its bytes ('dir', 'fifo', 'link')."""
    out = {}
    for dirpath, dirnames, filenames in os.walk(root):
        for name in dirnames + filenames:
            p = Path(dirpath) / name
            key = os.fsdecode(p.relative_to(root))
            if p.is_symlink():
                out[key] = "link:" + os.readlink(p)
            elif p.is_dir():
                out[key] = "dir"
            elif p.is_fifo():
                out[key] = "fifo"
            else:
                out[key] = hashlib.sha256(p.read_bytes()).hexdigest()
    return out


def strays(root: Path, allow_partial: bool = False) -> list[str]:
    """Half-written leftovers under ``root``: temporary ``.NAME.*.part``, ``.NAME.old-PID``, ``.OUT.partial``."""
    found = []
    for dirpath, dirnames, filenames in os.walk(root):
        if allow_partial:
            dirnames[:] = [d for d in dirnames if not d.endswith(".partial")]
        for name in dirnames + filenames:
            if STRAY.search(name):
                found.append(os.fsdecode(Path(dirpath, name).relative_to(root)))
    return found


def png_whole(path: Path) -> bool:
    """A PNG ends with its IEND chunk (what a cut-short write lacks)."""
    data = path.read_bytes()
    return data.startswith(b"\x89PNG\r\n\x1a\n") and data.endswith(b"IEND\xaeB`\x82")


def modes(root: Path) -> dict[str, int]:
    return {os.fsdecode(p.relative_to(root.parent)): p.stat().st_mode & 0o777 for p in [root, *root.rglob("*")]}


# ----------------------------------------------------------------------------- fixtures
FIXTURES = r'''
import json, sys
from pathlib import Path
import numpy as np
import OpenImageIO as oiio
from forensics.demo.prnu import sensor_model, simulated_set
from forensics.io.images import write_image
from forensics.prnu.fingerprint import Fingerprint

root = Path(sys.argv[1])
size = (96, 128)
rng = np.random.default_rng(26)
model = sensor_model("A", size, sigma_k=0.01)
for k in range(2):                                    # two simulated cameras, PRNU sigma_k 1 %
    images = simulated_set(model.realize(rng, [0.0]), 6, 0.0, 300 + k, f"cam{k}")
    for i in range(6):
        write_image(root / f"cam{k}" / f"{i}.png", images.load(i))
for name, value in (("black", 0), ("white", 255)):   # content-free sets
    for i in range(6):
        write_image(root / name / f"{i}.png", np.full(size, value, np.uint8))
tex = np.random.default_rng(5)
for i in range(3):                                    # a small textured set for manifests
    write_image(root / "tiny" / f"f{i}.png", tex.integers(20, 230, (24, 32)).astype(np.uint8))

def rgba(path, colour, alpha):
    spec = oiio.ImageSpec(colour.shape[1], colour.shape[0], 4, "uint8")
    spec.alpha_channel = 3
    spec.attribute("oiio:UnassociatedAlpha", 1)  # stored as given (PNG's own convention), not divided by alpha
    out = oiio.ImageOutput.create(str(path))
    path.parent.mkdir(parents=True, exist_ok=True)
    assert out.open(str(path), spec) and out.write_image(np.dstack([colour, np.full(colour.shape[:2], alpha, np.uint8)]))
    out.close()

for i in range(4):                                    # one colour set written as RGB and as RGBA
    colour = tex.integers(30, 220, (48, 64, 3)).astype(np.uint8)
    write_image(root / "rgb" / f"f{i}.png", colour)
    rgba(root / "rgba128" / f"f{i}.png", colour, 128)
    rgba(root / "rgba0" / f"f{i}.png", colour, 0)

spec = oiio.ImageSpec(32, 24, 3, "uint8")             # EXIF exposure 0 and a 1970 date: unknown, not values
spec.attribute("ExposureTime", 0.0)
spec.attribute("Exif:DateTimeOriginal", "1970:01:01 00:00:00")
out = oiio.ImageOutput.create(str(root / "exif0.jpg"))
assert out.open(str(root / "exif0.jpg"), spec) and out.write_image(tex.integers(0, 255, (24, 32, 3)).astype(np.uint8))
out.close()

big = np.random.default_rng(5).standard_normal((128, 160)).astype(np.float32)
Fingerprint(big, "full", 3.0, [], 8, (128, 160)).save(root / "fp" / "big.npz")
'''

DAMAGE = r'''
import json, sys
from pathlib import Path
import numpy as np
fp = Path(sys.argv[1])
raw = (fp / "cam0.npz").read_bytes()
(fp / "truncated.npz").write_bytes(raw[: len(raw) // 2])
with np.load(fp / "cam0.npz") as npz:
    k, meta = npz["K"], json.loads(str(npz["meta"][()]))
np.savez(fp / "nokey.npz", K=k, meta=np.array(json.dumps({x: v for x, v in meta.items() if x != "frame_shape"})))
np.savez(fp / "wrongtype.npz", K=k, meta=np.array(json.dumps({**meta, "n_images": "six"})))
np.savez(fp / "nan.npz", K=np.full_like(k, np.nan), meta=np.array(json.dumps(meta)))
'''

EDIT_META = r'''
import json, sys
import numpy as np
path = sys.argv[1]
with np.load(path) as npz:
    arrays = {k: npz[k] for k in npz.files}
meta = json.loads(str(arrays["meta"][()]))
meta.update(json.loads(sys.argv[2]))  # K and the rest unchanged: the file stays self-consistent
arrays["meta"] = np.array(json.dumps(meta))
with open(path, "wb") as handle:
    np.savez(handle, **arrays)
'''

SAME_K = r'''
import sys
import numpy as np
with np.load(sys.argv[1]) as a, np.load(sys.argv[2]) as b:
    print("same" if np.array_equal(a["K"], b["K"]) else "different")
'''


def python_of(forensics: str) -> str:
    """The interpreter of the tested install: the console script's ``#!`` line."""
    first = Path(forensics).read_bytes().split(b"\n", 1)[0]
    if first.startswith(b"#!") and Path(first[2:].decode().strip()).exists():
        return first[2:].decode().strip()
    return sys.executable


def png_bomb(path: Path, side: int = 50_000) -> None:
    """A 300 kB PNG whose header declares side² pixels (a decompression bomb); only its first rows are stored —
    the promise is a refusal from the header, before anything is decoded.  The padding chunk takes it past
    OpenImageIO's own size-ratio check (10,000 : 1), as a real zlib bomb (about 1,000 : 1) is."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return len(data).to_bytes(4, "big") + kind + data + zlib.crc32(kind + data).to_bytes(4, "big")
    ihdr = side.to_bytes(4, "big") * 2 + bytes([8, 0, 0, 0, 0])
    rows = zlib.compress(bytes(side + 1) * 200, 9)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"prVt", bytes(300_000))
                     + chunk(b"IDAT", rows) + chunk(b"IEND", b""))


class Fixtures:
    """Paths of the read-only inputs under ``root`` (made once; hashed after every case)."""

    def __init__(self, root: Path, run: Runner, python: str, quick: bool = False):
        """Make the fixtures; ``quick``: only what the quick cases read (scenes, the simulated cameras and
        constant sets, one fingerprint, the small sets), for the test suite."""
        self.root = root
        f = run.forensics
        sh = lambda *a: subprocess.run([*map(str, a)], cwd=root.parent, check=True, capture_output=True)  # noqa: E731
        sh(f, "simulate", "scenes", root / "scenes", "--count", "6", "--size", "96x72", "--seed", "1", "--quiet")
        sh(python, "-c", FIXTURES, root)
        sh(f, "fingerprint", "build", root / "cam0", "-o", root / "fp" / "cam0.npz", W, "1", "--quiet")
        os.mkfifo(root / "pipe.png")
        if quick:
            return
        sh(f, "simulate", "scenes", root / "bigscenes", "--count", "4", "--size", "320x240", "--rgb", "--seed", "3",
           "--quiet")
        sh(f, "simulate", "scenes", root / "lifetime", "--count", "16", "--size", "192x144", "--bits", "16",
           "--seed", "2", "--quiet")
        sh(f, "simulate", "scenes", root / "tifs", "--count", "2", "--size", "32x24", "--format", "tif",
           "--seed", "4", "--quiet")
        sh(f, "fingerprint", "build", root / "cam1", "-o", root / "fp" / "cam1.npz", W, "1", "--quiet")
        sh(f, "fingerprint", "build", root / "cam0", "-o", root / "fp" / "cam0c.npz", "--region", "center:64",
           W, "1", "--quiet")
        sh(python, "-c", DAMAGE, root / "fp")
        # A growth model from a simulated device seen at three ages (what `date --model` reads).
        sh(f, "simulate", "age", root / "scenes", root / "aged", "--sensor", "G", "--years", "0,4,8", "--seed", "1",
           "--rate-scale", "2000", "--start", "2000", W, "1", "--quiet")
        sh(f, "defects", "growth", *[root / "aged" / f"year_{a:03d}" for a in (0, 4, 8)], "-o", root / "model.json",
           W, "1", "--quiet")
        png_bomb(root / "bomb.png")

    def __getattr__(self, name: str) -> Path:
        return self.root / name


# ----------------------------------------------------------------------------- the cases
@dataclass
class Case:
    name: str
    defect: str
    expected: str
    body: Callable[["Ctx"], tuple[str, list[str]]]
    quick: bool = False


CASES: list[Case] = []


def case(name: str, defect: str, expected: str, quick: bool = False):
    def register(body):
        CASES.append(Case(name, defect, expected, body, quick))
        return body
    return register


@dataclass
class Ctx:
    """What a case gets: the runner, the fixtures, its own empty scratch folder and the worker count."""

    run: Runner
    fx: Fixtures
    work: Path
    workers: int
    python: str


def simple(name: str, defect: str, code: int, argv: Callable[[Ctx], list], *needles: str, quick: bool = False,
           json_out: bool = False, timeout: float = 120, allow_partial: bool = False,
           absent: Callable[[Ctx], list[Path]] = lambda c: []) -> None:
    """A case that is one command: its exit code, its one line holding ``needles``, nothing left behind."""
    expected = f"exit {code}" + (f", '{needles[0]}'" if needles else "")

    def body(c: Ctx) -> tuple[str, list[str]]:
        r = c.run(*argv(c), timeout=timeout)
        problems = check(r, code, *needles, json_out=json_out)
        problems += [f"left behind: {p}" for p in absent(c) if os.path.lexists(p)]
        problems += [f"stray: {s}" for s in strays(c.work, allow_partial)]
        return observed(r), problems

    case(name, defect, expected, quick)(body)


def copy_set(src: Path, dst: Path, manifest: str | bytes | None = None) -> Path:
    shutil.copytree(src, dst)
    if isinstance(manifest, str):
        (dst / "manifest.csv").write_text(manifest, encoding="utf-8")
    elif manifest is not None:
        (dst / "manifest.csv").write_bytes(manifest)
    return dst


W = "--workers"


def age_args(c: Ctx, src: Path, out: Path, workers: int | None = None) -> list:
    return ["simulate", "age", src, out, "--sensor", "H", "--years", "0:100:10", "--seed", "3", "--quiet",
            W, workers or c.workers]
