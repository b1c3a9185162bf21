#!/usr/bin/env bash
# Health check of the quincunx image: `GET /healthz` over bash's /dev/tcp, healthy on 200.
# bash is already in debian:bookworm-slim, so the image needs no curl (and none of the
# libraries curl pulls in). Usage: healthcheck.sh [HOST [PORT]] (default 127.0.0.1 8080).
set -euo pipefail
host="${1:-127.0.0.1}"
port="${2:-8080}"
exec 3<>"/dev/tcp/${host}/${port}"
printf 'GET /healthz HTTP/1.1\r\nHost: %s\r\nConnection: close\r\n\r\n' "${host}" >&3
IFS= read -r -t 5 status <&3
[[ "${status}" == "HTTP/1.1 200 "* ]]
