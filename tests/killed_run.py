"""A ``run.py`` command killed with SIGKILL once it has written a given frame: what a crash or an
out-of-time job leaves behind, for the resume tests."""
import os
import pathlib
import signal
import subprocess
import sys
import time

REPOSITORY = pathlib.Path(__file__).resolve().parents[1]


def kill_after_frame(arguments: list[str], folder: pathlib.Path, frame: int, timeout: float = 120.0) -> None:
    """Run ``run.py arguments`` in a subprocess and kill it (-9) as soon as ``folder`` holds
    ``frames/<frame>.json``; fails if the command ended by itself first."""
    process = subprocess.Popen([sys.executable, str(REPOSITORY / "run.py"), *arguments], cwd=REPOSITORY,
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                               env={**os.environ, "PYTHONPATH": str(REPOSITORY)})
    marker = folder / "frames" / f"{frame:06d}.json"
    deadline = time.monotonic() + timeout
    while not marker.exists() and process.poll() is None and time.monotonic() < deadline:
        time.sleep(0.02)
    process.send_signal(signal.SIGKILL)
    process.wait()
    assert process.returncode == -signal.SIGKILL, f"run.py {arguments[0]} ended before it could be killed"
