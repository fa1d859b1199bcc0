"""tools/failure_summary.py on the JUnit XML of a real pytest run (a small suite in a temporary folder)."""

from __future__ import annotations

import subprocess
import sys

from polycc.testing.files import CHECKOUT

sys.path.insert(0, str(CHECKOUT / "tools"))
from failure_summary import summarise  # noqa: E402


def test_the_summary_names_each_failure_with_its_message_and_duration(tmp_path):
    (tmp_path / "test_small.py").write_text(
        "import time\n"
        "def test_ok():\n    time.sleep(0.3)\n"
        "def test_bad():\n    assert 1 + 1 == 3, 'arithmetic is off'\n"
        "def test_boom():\n    raise RuntimeError('the simulator stopped answering')\n")
    report = tmp_path / "r.xml"
    rc = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-p", "no:randomly",
                         f"--junitxml={report}", f"--rootdir={tmp_path}", "-c", "/dev/null", str(tmp_path)],
                        cwd=tmp_path, capture_output=True, text=True).returncode
    assert rc == 1
    text = summarise(report, rc)
    assert "FAILURE test_small.py::test_bad" in text and "arithmetic is off" in text
    assert "FAILURE test_small.py::test_boom" in text and "the simulator stopped answering" in text
    assert "slowest: test_small.py::test_ok 0 s" in text
    assert text.rstrip().endswith("1 passed, 2 failed, 0 error, 0 skipped (of 3 with a result)")
    assert "INTERNALERROR" not in text and "INTERNALERROR" in summarise(report, 3)


def test_no_report_is_said_not_raised(tmp_path):
    assert "no report at" in summarise(tmp_path / "missing.xml")
