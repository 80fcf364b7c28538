"""compose.yaml, checked without a Docker engine: the services, their ports, volumes,
healthchecks and profiles, and that no secret is written in the file."""

from __future__ import annotations

import ipaddress
import re
from pathlib import Path
from typing import Any

import pytest
import yaml

from server.config import SECRETS_DIR_VARIABLE, Settings, get_settings

ROOT = Path(__file__).resolve().parents[2]
COMPOSE: dict[str, Any] = yaml.safe_load((ROOT / "compose.yaml").read_text())
SERVICES: dict[str, Any] = COMPOSE["services"]
SECRET_WORDS = re.compile(r"TOKEN|PASSWORD|SECRET|KEY", re.I)


def environment(service: str) -> dict[str, str]:
    return {k: str(v) for k, v in (SERVICES[service].get("environment") or {}).items()}


def test_services_and_profiles():
    assert set(SERVICES) == {"db", "proxy", "api", "ray-head", "ray-worker"}
    assert SERVICES["api"]["deploy"]["replicas"] == 2
    assert "profiles" not in SERVICES["api"] and "profiles" not in SERVICES["db"]
    assert SERVICES["ray-head"]["profiles"] == ["ray"] == SERVICES["ray-worker"]["profiles"]
    assert SERVICES["api"]["depends_on"]["db"]["condition"] == "service_healthy"
    # the API waits for the Ray head when the profile runs it, and starts without it otherwise
    assert SERVICES["api"]["depends_on"]["ray-head"] == {
        "condition": "service_healthy",
        "required": False,
    }
    assert SERVICES["ray-worker"]["depends_on"]["ray-head"]["condition"] == "service_healthy"
    images = {SERVICES[s]["image"] for s in ("api", "ray-head", "ray-worker")}
    assert images == {"srd-auction:latest"}  # the same code on the API and the Ray nodes
    assert SERVICES["api"]["build"]["args"]["EXTRAS"] == "ray"


def test_every_service_checks_its_health():
    for name, service in SERVICES.items():
        test = service["healthcheck"]["test"]
        assert test[0] == "CMD" and len(test) > 1, name
    assert SERVICES["api"]["healthcheck"]["test"] == ["CMD", "srd", "healthcheck"]
    assert SERVICES["db"]["healthcheck"]["test"][1] == "pg_isready"
    assert SERVICES["ray-head"]["healthcheck"]["test"][1:3] == ["ray", "health-check"]


def test_ports_only_the_proxy_is_public_and_the_api_on_the_loopback():
    assert SERVICES["api"]["ports"] == ["127.0.0.1:8000-8001:8000"]  # a port per replica
    assert SERVICES["proxy"]["ports"] == ["${SRD_HTTPS_PORT:-443}:443", "${SRD_HTTP_PORT:-80}:80"]
    for name in ("db", "ray-head", "ray-worker"):
        assert "ports" not in SERVICES[name], name
    head = SERVICES["ray-head"]["command"]
    assert "--dashboard-host=127.0.0.1" in head and "--head" in head


def test_volumes_keep_the_database_and_the_shared_artifacts():
    assert SERVICES["db"]["volumes"] == ["pgdata:/var/lib/postgresql/data"]
    assert SERVICES["api"]["volumes"] == ["srd-data:/data"]
    assert environment("api")["SRD_DATA_DIR"] == "/data"
    assert set(COMPOSE["volumes"]) == {"pgdata", "srd-data", "proxy-certs"}


def test_no_secret_is_written_in_the_file():
    for name in SERVICES:
        for key, value in environment(name).items():
            if SECRET_WORDS.search(key):  # a path to a secret file, or Ray's mode switch
                assert value.startswith("/run/secrets") or value == "token", (name, key)
            assert "@" not in value, (name, key)  # no credentials in a URL
    api = environment("api")
    assert "SRD_DATABASE_URL" not in api and "SRD_ADMIN_TOKEN" not in api
    assert api[SECRETS_DIR_VARIABLE] == "/run/secrets"
    assert {"srd_database_url", "srd_admin_token"} <= set(SERVICES["api"]["secrets"])
    for name, secret in COMPOSE["secrets"].items():
        assert secret == {"file": f"./secrets/{name}"}, name


def image_environment() -> dict[str, str]:
    """The variables the Dockerfile's ENV instructions set (``ENV A=1 \\`` continued)."""
    text = (ROOT / "Dockerfile").read_text().replace("\\\n", " ")
    found: dict[str, str] = {}
    for line in text.splitlines():
        if line.startswith("ENV "):
            found.update(pair.split("=", 1) for pair in line[4:].split())
    return found


def test_the_image_sets_no_variable_that_would_hide_a_secret_file():
    """A variable wins over its secret file: had the image set SRD_DATABASE_URL (it did, to
    SQLite), the replicas would never read the PostgreSQL URL compose gives them as a file."""
    image = image_environment()
    assert image["SRD_DATA_DIR"] == "/data"  # the parser reads the ENV lines
    for secret in SERVICES["api"]["secrets"]:
        assert secret.upper() not in image, secret


def test_ray_nodes_and_api_use_token_authentication():
    for name in ("api", "ray-head", "ray-worker"):
        env = environment(name)
        assert env["RAY_AUTH_MODE"] == "token", name
        assert env["RAY_AUTH_TOKEN_PATH"] == "/run/secrets/ray_auth_token", name
        assert "ray_auth_token" in SERVICES[name]["secrets"], name
    assert environment("api")["SRD_RAY_ADDRESS"] == "ray-head:6379"


def test_settings_read_the_secret_files(tmp_path, monkeypatch):
    (tmp_path / "srd_admin_token").write_text("a-token-read-from-a-file-0123456789\n")
    (tmp_path / "srd_database_url").write_text(f"sqlite:///{tmp_path / 'x.db'}\n")
    monkeypatch.setenv(SECRETS_DIR_VARIABLE, str(tmp_path))
    monkeypatch.delenv("SRD_DATABASE_URL", raising=False)
    monkeypatch.delenv("SRD_ADMIN_TOKEN", raising=False)
    get_settings.cache_clear()
    try:
        settings = get_settings()
        assert settings.admin_token is not None
        assert settings.admin_token.get_secret_value() == "a-token-read-from-a-file-0123456789"
        assert settings.database_url == f"sqlite:///{tmp_path / 'x.db'}"
        monkeypatch.setenv("SRD_DATABASE_URL", "sqlite:///from-the-environment.db")
        get_settings.cache_clear()
        assert get_settings().database_url == "sqlite:///from-the-environment.db"  # env wins
    finally:
        get_settings.cache_clear()


@pytest.mark.parametrize("service", ["api", "ray-head", "ray-worker"])
def test_commands_use_exec_form(service):
    assert isinstance(SERVICES[service]["command"], list)


NGINX = (ROOT / "deploy" / "nginx.conf").read_text()


def nginx_directives(name: str) -> list[str]:
    """The arguments of every ``name`` directive of deploy/nginx.conf."""
    return [m.strip() for m in re.findall(rf"^\s*{name}\s+([^;]*);", NGINX, flags=re.M)]


def test_the_api_trusts_forwarded_for_from_the_proxy_only():
    proxy = SERVICES["proxy"]["networks"]["backend"]["ipv4_address"]
    subnet = COMPOSE["networks"]["backend"]["ipam"]["config"][0]["subnet"]
    assert ipaddress.ip_address(proxy) in ipaddress.ip_network(subnet)
    assert environment("api")["SRD_TRUSTED_PROXIES"] == proxy
    assert Settings.model_fields["trusted_proxies"].default == ""  # nobody by default
    # The proxy replaces the header with the address it sees: a client cannot add to it.
    assert nginx_directives("proxy_set_header").count("X-Forwarded-For $remote_addr") == 1
    # ... on every path, round sockets included: a location setting a header of its own
    # would inherit none of the server's, and every client would be the proxy's address.
    locations = re.findall(r"^\s*location\s[^{]*\{([^}]*)\}", NGINX, flags=re.M)
    assert len(locations) == 3
    assert [block for block in locations if "proxy_set_header" in block] == []
    assert "Upgrade $http_upgrade" in nginx_directives("proxy_set_header")
    assert "Connection $connection_upgrade" in nginx_directives("proxy_set_header")
    assert SERVICES["proxy"]["depends_on"]["api"]["condition"] == "service_healthy"


def test_the_api_takes_the_web_views_writes_at_the_name_the_proxy_serves():
    """Pages reach the API under the proxy's public name (nginx passes ``Host $host``); the
    API takes browsers' writes at that name only, besides IP addresses and localhost."""
    assert "Host $host" in nginx_directives("proxy_set_header")
    public = SERVICES["proxy"]["environment"]["SRD_PUBLIC_HOST"]
    assert environment("api")["SRD_ALLOWED_HOSTS"] == public == "${SRD_PUBLIC_HOST:-localhost}"


def test_the_proxy_terminates_tls_and_limits_each_address():
    assert nginx_directives("listen") == ["80", "443 ssl"]
    assert nginx_directives("ssl_certificate") == ["/etc/nginx/certs/tls.crt"]
    assert SERVICES["proxy"]["volumes"] == ["proxy-certs:/etc/nginx/certs"]
    assert nginx_directives("limit_conn") == ["per_address 256"]
    assert nginx_directives("limit_req") == ["zone=request_rate burst=200 nodelay"]
    assert nginx_directives("limit_conn_status") == ["429"] == nginx_directives("limit_req_status")
    for name in ("client_header_timeout", "client_body_timeout", "keepalive_timeout"):
        (value,) = nginx_directives(name)
        assert value.endswith("s") and 0 < int(value[:-1]) <= 30, name
    (body,) = nginx_directives("client_max_body_size")
    assert body == f"{Settings.model_fields['max_body_bytes'].default // 1024}k"
    assert "$request " not in NGINX and '$request_uri"' not in NGINX  # no query string logged
    assert SERVICES["proxy"]["healthcheck"]["test"][:2] == ["CMD", "curl"]
