#!/bin/sh
# First start: a self-signed certificate for SRD_PUBLIC_HOST, unless one is already in
# /etc/nginx/certs (a real one mounted there, or the one made at an earlier start).
set -eu
CERTS=/etc/nginx/certs
if [ ! -s "$CERTS/tls.crt" ] || [ ! -s "$CERTS/tls.key" ]; then
    host="${SRD_PUBLIC_HOST:-localhost}"
    openssl req -x509 -newkey rsa:2048 -nodes -days 825 -subj "/CN=$host" \
        -addext "subjectAltName=DNS:$host" \
        -keyout "$CERTS/tls.key" -out "$CERTS/tls.crt"
    chmod 600 "$CERTS/tls.key"
    echo "proxy: generated a self-signed certificate for $host" >&2
fi
