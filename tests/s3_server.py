"""A real S3 endpoint for the tests: moto's standalone server (``moto_server``, from the
``moto[server]`` dev dependency) in a process of its own on a free loopback port.

Credentials are checked, as a real bucket's are: an IAM user with an ``s3:*`` policy is
made while the server still takes anonymous calls, then authentication is switched on
(moto's ``/moto-api/reset-auth``), so a wrong key is refused (``InvalidAccessKeyId``).
``pause()``/``resume()`` stop and continue the process (SIGSTOP/SIGCONT): an endpoint
that stops answering mid-job, which keeps its buckets (a restarted moto would not).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
import urllib.error
import urllib.request
import uuid
from pathlib import Path
from typing import Any

from tests.api.support import free_port

REGION = "us-east-1"
POLICY = {
    "Version": "2012-10-17",
    "Statement": [{"Effect": "Allow", "Action": "s3:*", "Resource": "*"}],
}
PART_BYTES = 5 << 20  # S3's smallest part: multipart uploads start early in the tests


def _moto_server() -> list[str]:
    exe = Path(sys.executable).parent / "moto_server"
    return [str(exe)] if exe.exists() else [sys.executable, "-m", "moto.server"]


class S3Server:
    """moto_server with authentication on; ``client()`` has the valid credentials."""

    def __init__(self, root: Path) -> None:
        self.root = root
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.proc: subprocess.Popen[bytes] | None = None
        self.access_key = self.secret_key = ""

    def start(self) -> S3Server:
        self.root.mkdir(parents=True, exist_ok=True)
        env = {k: v for k, v in os.environ.items() if not k.startswith(("AWS_", "MOTO_"))}
        log = open(self.root / "moto.log", "ab")  # noqa: SIM115 (the process owns it)
        self.proc = subprocess.Popen(
            [*_moto_server(), "-H", "127.0.0.1", "-p", str(self.port)],
            stdout=log,
            stderr=subprocess.STDOUT,
            env=env,
            start_new_session=True,
        )
        deadline = time.monotonic() + 30
        while True:
            try:
                urllib.request.urlopen(f"{self.url}/moto-api/", timeout=1).read()
                break
            except (OSError, urllib.error.URLError):
                if self.proc.poll() is not None or time.monotonic() > deadline:
                    raise RuntimeError(f"moto_server did not start: {self.log()[-2000:]}") from None
                time.sleep(0.1)
        self._enable_auth()
        return self

    def _enable_auth(self) -> None:
        iam = self._boto("iam", "anonymous", "anonymous")
        user = f"glint-{uuid.uuid4().hex[:8]}"
        iam.create_user(UserName=user)
        key = iam.create_access_key(UserName=user)["AccessKey"]
        iam.put_user_policy(UserName=user, PolicyName="s3", PolicyDocument=json.dumps(POLICY))
        self.access_key, self.secret_key = key["AccessKeyId"], key["SecretAccessKey"]
        req = urllib.request.Request(
            f"{self.url}/moto-api/reset-auth",
            data=b"0",
            method="POST",
            headers={"Content-Type": "text/plain"},
        )
        urllib.request.urlopen(req, timeout=10).read()

    def _boto(self, service: str, key: str, secret: str) -> Any:
        import boto3
        from botocore.config import Config

        return boto3.client(
            service,
            endpoint_url=self.url,
            region_name=REGION,
            aws_access_key_id=key,
            aws_secret_access_key=secret,
            config=Config(s3={"addressing_style": "path"}, retries={"max_attempts": 2}),
        )

    def client(self) -> Any:
        """A boto3 S3 client with valid credentials: what the tests inspect the bucket with."""
        return self._boto("s3", self.access_key, self.secret_key)

    def bucket(self, prefix: str = "glint") -> str:
        name = f"{prefix}-{uuid.uuid4().hex[:10]}"
        self.client().create_bucket(Bucket=name)
        return name

    def keys(self, bucket: str, prefix: str = "") -> list[str]:
        pages = (
            self.client().get_paginator("list_objects_v2").paginate(Bucket=bucket, Prefix=prefix)
        )
        return sorted(o["Key"] for page in pages for o in page.get("Contents", []))

    def uploads(self, bucket: str) -> list[dict[str, Any]]:
        """Multipart uploads in progress (neither completed nor aborted)."""
        return list(self.client().list_multipart_uploads(Bucket=bucket).get("Uploads", []))

    def settings(self, bucket: str, **overrides: Any) -> dict[str, Any]:
        """Settings fields of a store in ``bucket`` on this server (short timeouts)."""
        values: dict[str, Any] = {
            "store_url": f"s3://{bucket}/glint",
            "s3_endpoint_url": self.url,
            "s3_region": REGION,
            "s3_access_key_id": self.access_key,
            "s3_secret_access_key": self.secret_key,
            "store_timeout_s": 2.0,
            "store_part_bytes": PART_BYTES,
            "store_retry_s": 60.0,
        }
        values.update(overrides)
        return values

    def env(self, bucket: str, **overrides: Any) -> dict[str, str]:
        """The same as ``GLINT_*`` variables, for a worker process."""
        return {f"GLINT_{k.upper()}": str(v) for k, v in self.settings(bucket, **overrides).items()}

    def pause(self) -> None:
        """Stop answering (the process is stopped; connections hang, then time out)."""
        assert self.proc is not None
        os.kill(self.proc.pid, signal.SIGSTOP)

    def resume(self) -> None:
        assert self.proc is not None
        os.kill(self.proc.pid, signal.SIGCONT)

    def log(self) -> str:
        path = self.root / "moto.log"
        return path.read_text(errors="replace") if path.exists() else ""

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.resume()
            self.proc.terminate()
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)
        self.proc = None
