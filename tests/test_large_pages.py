"""The command line's restart with huge pages for malloc (facepipe.cli.large_pages)."""

import subprocess
import sys

import pytest

from facepipe.cli import large_pages
from facepipe.cli.large_pages import TUNABLE, large_page_environment


@pytest.fixture
def madvise_linux(tmp_path, monkeypatch):
    """A Linux with glibc 2.36 and transparent huge pages in madvise mode."""
    mode = tmp_path / "enabled"
    mode.write_text("always [madvise] never\n")
    monkeypatch.setattr(large_pages, "THP_MODE", mode)
    monkeypatch.setattr(large_pages.sys, "platform", "linux")
    monkeypatch.setattr(large_pages.os, "confstr", lambda name: "glibc 2.36")
    return mode


def test_the_tunable_is_added_where_it_helps(madvise_linux):
    assert large_page_environment({"HOME": "/h"}) == {"HOME": "/h", "GLIBC_TUNABLES": f"{TUNABLE}=1"}
    # the user's own tunables are kept
    env = large_page_environment({"GLIBC_TUNABLES": "glibc.malloc.check=0"})
    assert env["GLIBC_TUNABLES"] == f"glibc.malloc.check=0:{TUNABLE}=1"


@pytest.mark.parametrize("case", ["opted out", "opted out in words", "set already", "user's own value", "thp always",
                                  "thp never", "no thp file", "old glibc", "musl", "not linux"])
def test_nothing_changes_where_it_would_not_help(madvise_linux, monkeypatch, case):
    environ = {}
    if case == "opted out":
        environ = {"FACEPIPE_LARGE_PAGES": "0"}
    elif case == "opted out in words":
        environ = {"FACEPIPE_LARGE_PAGES": " Off"}
    elif case == "set already":
        environ = {"GLIBC_TUNABLES": f"{TUNABLE}=1"}
    elif case == "user's own value":
        environ = {"GLIBC_TUNABLES": f"{TUNABLE}=0"}
    elif case == "thp always":
        madvise_linux.write_text("[always] madvise never\n")
    elif case == "thp never":
        madvise_linux.write_text("always madvise [never]\n")
    elif case == "no thp file":
        madvise_linux.unlink()
    elif case == "old glibc":
        monkeypatch.setattr(large_pages.os, "confstr", lambda name: "glibc 2.31")
    elif case == "musl":
        def no_such_name(name):
            raise ValueError("unrecognized configuration name")  # what a C library without it gives

        monkeypatch.setattr(large_pages.os, "confstr", no_such_name)
    else:
        monkeypatch.setattr(large_pages.sys, "platform", "darwin")
    assert large_page_environment(environ) is None


def test_the_process_restarts_once_with_its_arguments(tmp_path):
    if large_page_environment() is None:
        pytest.skip("huge pages for malloc would change nothing on this machine (see facepipe.cli.large_pages)")
    script = tmp_path / "start.py"
    script.write_text("import os, sys\n"
                      "print('start', flush=True)\n"
                      "from facepipe.cli.large_pages import restart_with_large_pages\n"
                      "restart_with_large_pages()\n"
                      "print('run', os.environ['GLIBC_TUNABLES'], sys.argv[1:])\n")
    out = subprocess.run([sys.executable, str(script), "a", "b c"], capture_output=True, text=True, check=True).stdout
    assert out.splitlines() == ["start", "start", f"run {TUNABLE}=1 ['a', 'b c']"]


def test_the_command_line_runs_after_its_restart():
    done = subprocess.run([sys.executable, "-m", "facepipe", "--help"], capture_output=True, text=True)
    assert done.returncode == 0 and "Usage:" in done.stdout and done.stderr == ""


def test_no_restart_without_an_interpreter_to_run(madvise_linux, monkeypatch):
    """An embedding interpreter without a binary (sys.executable empty or None) goes on as it is."""
    calls = []
    monkeypatch.setattr(large_pages.os, "execve", lambda *a: calls.append(a))
    monkeypatch.delenv("GLIBC_TUNABLES", raising=False)
    monkeypatch.delenv("FACEPIPE_LARGE_PAGES", raising=False)
    for executable in ("", None):
        monkeypatch.setattr(large_pages.sys, "executable", executable)
        large_pages.restart_with_large_pages()
    assert calls == []
    monkeypatch.setattr(large_pages.sys, "executable", "/usr/bin/python3")
    large_pages.restart_with_large_pages()
    assert len(calls) == 1 and calls[0][0] == "/usr/bin/python3"
    assert calls[0][2]["GLIBC_TUNABLES"] == f"{TUNABLE}=1"
