"""Session 48: smaller fixes left open by session 47's note."""

import socket

import pytest

from fusedmosaic.cli import main


@pytest.fixture(scope="module")
def pcle(tmp_path_factory):
    root = tmp_path_factory.mktemp("s48") / "pcle"
    assert main(["--quiet", "simulate", "pcle", str(root), "--n-frames", "6"]) == 0
    return root


def _closed_port() -> int:
    with socket.create_server(("127.0.0.1", 0)) as server:
        return server.getsockname()[1]


def test_live_says_connecting_only_once_out_is_accepted(pcle, tmp_path, capsys):
    """`live` printed "live: connecting to ..." and then refused OUT: nothing had connected."""
    out, record = tmp_path / "out", tmp_path / "rec"
    out.mkdir()
    (out / "report.md").write_text("my notes")
    port = _closed_port()
    args = ["live", f"127.0.0.1:{port}", "--camera", str(pcle / "camera.yaml"), "--method",
            "ncc", "--record", str(record), "--out", str(out)]
    assert main(args) == 2
    said = capsys.readouterr()
    assert "exists and fusedmosaic did not write it" in said.err
    assert "live: connecting" not in said.out + said.err
    (out / "report.md").unlink()
    assert main(args) != 0  # (nothing listens on the port)
    said = capsys.readouterr()
    assert f"live: connecting to 127.0.0.1:{port}" in said.out
