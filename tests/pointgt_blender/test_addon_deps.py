"""Dependency helpers of the add-on (no Blender needed): the pip command and site-packages checks."""
from __future__ import annotations

import sys
import sysconfig

from pointgt_blender.bridge import deps


def test_pip_command_installs_pinned_cpu_torch_into_target_with_blenders_python(tmp_path):
    cmd = deps.pip_install_command(tmp_path)
    assert cmd[:4] == [sys.executable, "-m", "pip", "install"]
    assert cmd[cmd.index("--target") + 1] == str(tmp_path)
    assert cmd[cmd.index("--index-url") + 1] == "https://download.pytorch.org/whl/cpu"
    assert cmd[-1] == "torch==2.13.0"


def test_pip_command_offline_uses_only_the_wheel_folder(tmp_path):
    cmd = deps.pip_install_command(tmp_path, ("probe",), index_url=None, find_links="/wheels")
    assert "--no-index" in cmd and "--index-url" not in cmd
    assert cmd[cmd.index("--find-links") + 1] == "/wheels" and cmd[-1] == "probe"


def test_site_packages_check_names_each_problem(tmp_path):
    assert "folder not found" in deps.check_site_packages(tmp_path / "nope")
    assert "no torch package" in deps.check_site_packages(tmp_path)
    (tmp_path / "torch").mkdir()
    (tmp_path / "torch" / "__init__.py").write_text("")
    (tmp_path / "torch" / "_C.cpython-399-x86_64-linux-gnu.so").write_bytes(b"")
    assert "another Python" in deps.check_site_packages(tmp_path)
    (tmp_path / "torch" / ("_C" + sysconfig.get_config_var("EXT_SUFFIX"))).write_bytes(b"")
    assert deps.check_site_packages(tmp_path) == ""


def test_site_dirs_are_appended_once_and_removed(tmp_path):
    try:
        assert deps.add_site_dir(tmp_path) is True
        assert deps.add_site_dir(tmp_path) is False and sys.path.count(str(tmp_path)) == 1
        assert sys.path[-1] == str(tmp_path)  # appended: Blender's own modules keep priority
        assert deps.add_site_dir(tmp_path / "missing") is False
    finally:
        deps.remove_site_dir(tmp_path)
    assert str(tmp_path) not in sys.path


def test_status_message_says_how_to_fix():
    st = deps.TorchStatus(False, problem="ImportError: no torch. Install it from the add-on preferences")
    assert st.message.startswith("PyTorch is missing") and "preferences" in st.message
    assert deps.tail("a\nb\nc\n", 2) == "b\nc"
