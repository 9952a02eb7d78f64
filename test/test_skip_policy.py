"""A skip that is not for missing hardware fails (conftest.HARDWARE_SKIPS): a broken install
cannot turn CI green by skipping the tests it breaks."""

from pathlib import Path

pytest_plugins = ["pytester"]


def test_a_missing_module_fails_and_missing_hardware_skips(pytester):
    pytester.makeconftest((Path(__file__).parent / "conftest.py").read_text())
    pytester.makepyfile("""
        import pytest

        def test_missing_module():
            pytest.importorskip("w2e_no_such_module")

        @pytest.mark.skipif(True, reason="needs a CUDA device")
        def test_no_gpu():
            pass
    """)
    result = pytester.runpytest_subprocess("-q")
    result.assert_outcomes(failed=1, skipped=1)
    result.stdout.fnmatch_lines(["*not missing hardware*w2e_no_such_module*"])
