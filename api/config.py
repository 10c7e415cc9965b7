"""Service configuration: where data lives, how it binds, limits; from arguments or env."""

from __future__ import annotations

import ipaddress
import os
from dataclasses import dataclass, field
from pathlib import Path

DEFAULT_MAX_UPLOAD_BYTES = 512 * 1024 * 1024
# Bodies parsed as JSON (everything but file uploads): ample room over the largest real
# one (an extreme full-control plan is 270 KB; see api/body_limits.py).
DEFAULT_MAX_JSON_BYTES = 4 * 1024 * 1024
DEFAULT_SPACE_RESERVE_BYTES = 16 << 20  # held for the database on a full disk (api/storage.py)
DEFAULT_MIN_FREE_BYTES = 32 << 20  # kept free beyond a capture's estimate


@dataclass(frozen=True)
class ServiceConfig:
    """Everything `create_app` needs; env names are PHASECAL_<FIELD> (upper case)."""

    data_dir: Path = field(default_factory=lambda: Path("phasecal-data"))
    host: str = "127.0.0.1"
    port: int = 8000
    token: str | None = None
    rig: str = "simulated"
    executor: str | None = None
    max_upload_bytes: int = DEFAULT_MAX_UPLOAD_BYTES
    max_json_bytes: int = DEFAULT_MAX_JSON_BYTES
    rigs_dir: Path | None = None  # operator rig files (*.toml/*.json), one rig each
    aravis_addresses: tuple[str, ...] = ()  # Aravis cameras GET /devices lists (no broadcast)
    space_reserve_bytes: int = DEFAULT_SPACE_RESERVE_BYTES
    min_free_bytes: int = DEFAULT_MIN_FREE_BYTES

    @classmethod
    def from_env(cls, **overrides: object) -> ServiceConfig:
        """Defaults, then PHASECAL_* environment variables, then explicit non-None overrides."""
        env = os.environ
        values: dict[str, object] = {}
        if env.get("PHASECAL_DATA_DIR"):
            values["data_dir"] = Path(env["PHASECAL_DATA_DIR"])
        if env.get("PHASECAL_TOKEN_FILE"):
            values["token"] = read_token_file(env["PHASECAL_TOKEN_FILE"])
        if env.get("PHASECAL_TOKEN"):
            values["token"] = env["PHASECAL_TOKEN"]
        if env.get("PHASECAL_RIG"):
            values["rig"] = env["PHASECAL_RIG"]
        if env.get("PHASECAL_RIGS_DIR"):
            values["rigs_dir"] = Path(env["PHASECAL_RIGS_DIR"])
        if env.get("PHASECAL_ARAVIS_ADDRESSES"):
            values["aravis_addresses"] = tuple(env["PHASECAL_ARAVIS_ADDRESSES"].split(","))
        if env.get("PHASECAL_DASK"):
            values["executor"] = env["PHASECAL_DASK"]
        for key in ("max_upload_bytes", "max_json_bytes"):
            name = f"PHASECAL_{key.upper()}"
            if env.get(name):
                raw = env[name]
                if not raw.isdigit():
                    raise ValueError(f"{name}: expected a byte count (integer), got {raw!r}")
                values[key] = int(raw)
        for key in ("space_reserve_bytes", "min_free_bytes"):
            name = f"PHASECAL_{key.upper()}"
            if env.get(name):
                if not env[name].isdigit():
                    raise ValueError(f"{name}: expected a byte count (integer), got {env[name]!r}")
                values[key] = int(env[name])
        values.update({k: v for k, v in overrides.items() if v is not None})
        for key in ("data_dir", "rigs_dir"):
            if key in values:
                values[key] = Path(str(values[key]))
        return cls(**values)  # type: ignore[arg-type]

    def check_security(self) -> None:
        """Refuse a non-loopback bind without an API token (ValueError names the fix)."""
        if not is_loopback(self.host) and not self.token:
            raise ValueError(
                f"--host {self.host}: binding to a non-loopback address requires an API token; "
                "set PHASECAL_TOKEN (or --token) and send it as 'Authorization: Bearer <token>'"
            )


def is_loopback(host: str) -> bool:
    """True for 'localhost' and loopback IP literals (127.0.0.0/8, ::1)."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def read_token_file(path: str | Path) -> str:
    """The API token from a file (first line, surrounding whitespace dropped).

    A token file or PHASECAL_TOKEN keeps the token out of `ps` (a `--token` argument is
    visible to every user of the machine).
    """
    p = Path(path)
    try:
        token = p.read_text(encoding="utf-8").strip().splitlines()
    except OSError as exc:
        raise ValueError(f"token file {p}: cannot be read ({exc.strerror})") from None
    if not token or not token[0].strip():
        raise ValueError(f"token file {p}: empty")
    return token[0].strip()
