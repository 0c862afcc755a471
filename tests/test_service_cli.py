"""``plenodust serve`` refuses settings it cannot honour, before starting anything."""

from __future__ import annotations

import pytest

from service.cli.main import main


@pytest.mark.parametrize(("argv", "message"), [
    (["--camera", "firewire"], "camera 'firewire': use usb, wifi:HOST[:PORT], simulated:DIR or none"),
    (["--executor", "spark://x"], "use local or dask://HOST:PORT"),
    (["--run", "../etc"], "run name '../etc'"),
    (["--workers", "0"], "workers"),
])
def test_serve_refuses_bad_options(argv, message, capsys, tmp_path) -> None:
    assert main(["serve", "--data", str(tmp_path), *argv]) == 2
    assert message in capsys.readouterr().out


def test_serve_refuses_bad_pipeline_parameters(monkeypatch, capsys, tmp_path) -> None:
    monkeypatch.setenv("PLENODUST_PIPELINE", '{"n_slices": 1}')
    assert main(["serve", "--data", str(tmp_path)]) == 2
    assert "n_slices" in capsys.readouterr().out
