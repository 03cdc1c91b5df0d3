"""The viewers whose controls write into the dataset listen on this machine only unless the user opens them, and
say their address; our excepthook is ours alone."""

from __future__ import annotations

import subprocess
import sys

import psutil

from splatreplace_ns.tools.sim import make_scene
from scenes import free_port


def listening_addresses(port: int) -> set:
    return {c.laddr.ip for c in psutil.net_connections(kind="tcp") if c.laddr and c.laddr.port == port
            and c.status == psutil.CONN_LISTEN}


def test_ns_train_viewer_listens_on_localhost_by_default(tmp_path):
    from splatreplace_ns.method.train import make_trainer_config, setup_trainer

    data = make_scene("tiny", tmp_path / "tiny", n_train=6, n_test=2).parent
    config = make_trainer_config(data, tmp_path / "runs", 2)
    config.vis = "viewer"  # the method's own viewer settings, as `ns-train splat-replace` gets them
    config.viewer.websocket_port = port = free_port()
    trainer = setup_trainer(config)
    try:
        assert listening_addresses(port) == {"127.0.0.1"}, listening_addresses(port)
        assert any(f"http://127.0.0.1:{port}" in line for line in trainer.viewer_state.viewer_info)
    finally:
        trainer.viewer_state.viser_server.stop()


def test_masks_command_viewer_defaults_to_localhost_and_can_be_opened():
    import tyro

    from splatreplace_ns.method.masks_command import MasksCommand

    assert tyro.cli(MasksCommand, args=["data"]).viewer_host == "127.0.0.1"
    assert tyro.cli(MasksCommand, args=["data", "--viewer-host", "0.0.0.0"]).viewer_host == "0.0.0.0"


def test_other_methods_keep_their_excepthook():
    """nerfstudio imports every method's config (ours too) for any method: importing ours changes nothing."""
    code = ("import sys; before = sys.excepthook; import splatreplace_ns.method.config, splatreplace_ns.cli; "
            "print(sys.excepthook is before)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.stdout.strip().splitlines()[-1] == "True", out.stderr[-2000:]
