"""The console entry points (``uabs_rl.cli.launch``): a reader that leaves the pipe
(``uabs-eval ... | head -1``) ends the output, not the command: its files are written
whole, and the exit status is the shell's for a broken pipe."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap


def test_a_command_piped_into_head_still_writes_its_files(tmp_path):
    (tmp_path / "talkative.py").write_text(textwrap.dedent("""
        import pathlib, sys
        def main():
            for i in range(200_000):  # far more than a pipe's buffer holds
                print(f"line {i}")
            pathlib.Path(sys.argv[1]).write_text("whole")
            print("and after the files")
            sys.exit(0)  # as uabs-eval's and uabs-report's run_main end
    """))
    done = tmp_path / "done.txt"
    code = ("import sys; sys.argv = ['talkative', sys.argv[1]]; "
            "from uabs_rl.cli.launch import _run; _run('talkative', 'main')")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), *sys.path])}
    proc = subprocess.Popen([sys.executable, "-c", code, str(done)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, env=env)
    assert proc.stdout.readline() == b"line 0\n"
    proc.stdout.close()  # as head -1 does
    err = proc.stderr.read().decode()
    assert proc.wait(timeout=60) == 141, err
    assert done.read_text() == "whole"
    assert "Traceback" not in err and "BrokenPipe" not in err, err
