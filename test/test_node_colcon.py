"""The colcon workspace build README documents: the exact line from README's code block, run in
a fresh workspace holding this project (its tracked files) under src/dtm_labeler, builds both
packages; the installed labeler_node then runs from install/ (with the installed
dtm_labeler_msgs) and labels frames over DDS.

The install is handed the kernels ``scripts/setup.sh`` compiled for this checkout: numba keys a
cached kernel on the source file's content, and looks for it beside the source, so the installed
copies find them. Without that the node's first start compiles them (20-30 s on 2 cores, as
README says); what the test checks is the build and the installed node, not the compiler."""
from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import node_helpers as H

README = H.REPO / "README.md"


def readme_colcon_line() -> str:
    """The one line of README's code blocks that runs ``colcon build`` (optionally after
    variable assignments)."""
    blocks = re.findall(r"```(?:bash|sh)?\n(.*?)```", README.read_text(), flags=re.S)
    lines = [ln.split("  #")[0].strip() for b in blocks for ln in b.splitlines()]
    found = [ln for ln in lines if re.match(r"^(\w+=\S+\s+)*colcon build\b", ln)]
    assert len(found) == 1, f"README must hold exactly one colcon build line, found {found}"
    return found[0]


def copy_project(dst: Path) -> None:
    """The files a clean clone has (git's tracked files; the whole tree without build output
    when this is not a git checkout)."""
    r = subprocess.run(["git", "ls-files", "-z"], cwd=H.REPO, capture_output=True)
    if r.returncode == 0 and r.stdout:
        for rel in r.stdout.decode().split("\0"):
            if rel and (H.REPO / rel).is_file():
                (dst / rel).parent.mkdir(parents=True, exist_ok=True)
                shutil.copy2(H.REPO / rel, dst / rel)
        return
    shutil.copytree(H.REPO, dst, ignore=shutil.ignore_patterns(".venv", "build", "install", "log", "results",
                                                               "__pycache__", "*.egg-info"))


def give_compiled_kernels(site: Path) -> int:
    """Copy this checkout's numba cache (``__pycache__/*.nbi``, ``*.nbc``) beside the installed
    package's sources of the same name; returns how many files were copied."""
    copied = 0
    for f in (H.REPO / "dtm_labeler").rglob("__pycache__/*.nb[ic]"):
        rel = f.relative_to(H.REPO)
        if (site / rel.parent.parent).is_dir():
            (site / rel.parent).mkdir(exist_ok=True)
            shutil.copy2(f, site / rel)
            copied += 1
    return copied


def test_readme_colcon_build_and_installed_node(tmp_path):
    line = readme_colcon_line()
    ws = tmp_path / "ws"
    copy_project(ws / "src" / "dtm_labeler")
    env = dict(os.environ, VIRTUAL_ENV=sys.prefix, PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}")
    r = subprocess.run(["bash", "-c", line], cwd=ws, env=env, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, (line, r.stdout[-3000:], r.stderr[-3000:])
    assert "2 packages finished" in r.stdout, r.stdout[-2000:]
    node_exe = ws / "install" / "dtm_labeler" / "lib" / "dtm_labeler" / "labeler_node"
    assert node_exe.is_file() and (ws / "install" / "dtm_labeler_msgs" / "share" / "dtm_labeler_msgs").is_dir()
    # sourcing the workspace makes its packages the ones imported
    probe = (f"source install/setup.bash && {sys.executable} -c 'import dtm_labeler, dtm_labeler_msgs.msg; "
             "print(dtm_labeler.__file__); print(dtm_labeler_msgs.__file__)'")
    r = subprocess.run(["bash", "-c", probe], cwd=ws, env=H.node_env(), capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    assert all(p.startswith(str(ws / "install")) for p in r.stdout.split()), r.stdout
    give_compiled_kernels(Path(r.stdout.split()[0]).parent.parent)
    # the installed node runs and labels
    wm = H.walk_model()
    run = f"source {ws}/install/setup.bash && exec {node_exe} \"$@\""
    proc = H.NodeProcess("t_colcon", params={"model_path": wm.path, "diagnostics_period_s": 0.1},
                         cmd=["bash", "-c", run, "labeler_node"])
    cl = None
    try:
        cl = H.NodeClient(proc)
        cl.wait_connected()
        # a wait, not a timing: without a kernel cache the first load compiles them
        cl.wait_diag(lambda d: d.get("model_status") == "loaded", 90, "model loaded")
        assert cl.run_frames(H.FrameFeed(wm, seed=8), 10) > 0.95
        assert proc.stop(signal.SIGINT) == 0
    finally:
        if cl is not None:
            cl.close()
        if proc.alive():
            proc.stop(signal.SIGKILL)
