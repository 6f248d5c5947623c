"""MosquittoBroker: starts a real mosquitto, restarts it on the same port, fails with a clear hint."""

from __future__ import annotations

import socket
from pathlib import Path

import pytest
from twin.rig import mosquitto as broker_mod
from twin.rig.mosquitto import BrokerError, MosquittoBroker, MosquittoNotFound

pytestmark = pytest.mark.slow


def _accepts(host: str, port: int) -> bool:
    try:
        with socket.create_connection((host, port), timeout=0.5):
            return True
    except OSError:
        return False


def test_fixture_broker_listens_on_loopback(mosquitto: MosquittoBroker) -> None:
    assert mosquitto.host == "127.0.0.1"
    assert mosquitto.url == f"mqtt://127.0.0.1:{mosquitto.port}"
    assert mosquitto.running
    assert _accepts(mosquitto.host, mosquitto.port)
    config = mosquitto.config_path.read_text()
    assert f"listener {mosquitto.port} 127.0.0.1" in config
    assert "allow_anonymous true" in config
    assert "persistence false" in config


def test_stop_restart_same_port(mosquitto: MosquittoBroker) -> None:
    port = mosquitto.port
    mosquitto.stop()
    assert not mosquitto.running
    assert not _accepts("127.0.0.1", port)
    mosquitto.restart()
    assert mosquitto.port == port
    assert _accepts("127.0.0.1", port)
    mosquitto.restart(hard=True)
    assert mosquitto.port == port and mosquitto.running
    assert "mosquitto version" in mosquitto.log_path.read_text()


def test_context_manager_cleans_up(tmp_path: Path) -> None:
    with MosquittoBroker() as broker:
        workdir = broker.workdir
        port = broker.port
        assert _accepts("127.0.0.1", port)
    assert not broker.running
    assert not workdir.exists()


def test_busy_port_is_reported_with_log(mosquitto: MosquittoBroker, tmp_path: Path) -> None:
    clash = MosquittoBroker(mosquitto.port, workdir=tmp_path / "clash", start_timeout=3.0)
    with pytest.raises(BrokerError, match=r"port \d+ .*in use"):
        clash.start()
    assert not clash.running


def test_missing_binary_names_the_fix(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(broker_mod.shutil, "which", lambda _name: None)
    monkeypatch.setattr(broker_mod, "_SEARCH_DIRS", ("/nonexistent-dir",))
    with pytest.raises(MosquittoNotFound, match="make setup"):
        MosquittoBroker()
