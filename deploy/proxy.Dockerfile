# The compose deployment's front door: nginx with openssl, for the self-signed certificate
# made at first start (deploy/proxy-certificate.sh), and curl for its health check.
# Build: docker build -f deploy/proxy.Dockerfile -t srd-auction-proxy .
FROM nginx:1.27-bookworm

# Not pinned to versions: Debian replaces a package version when it ships a security fix.
# hadolint ignore=DL3008
RUN apt-get update \
    && apt-get install -y --no-install-recommends openssl curl \
    && rm -rf /var/lib/apt/lists/* \
    && mkdir -p /etc/nginx/certs

COPY deploy/nginx.conf /etc/nginx/nginx.conf
COPY deploy/proxy-certificate.sh /docker-entrypoint.d/05-certificate.sh
VOLUME ["/etc/nginx/certs"]
EXPOSE 80 443
HEALTHCHECK --interval=30s --timeout=5s --start-period=10s \
    CMD ["curl", "--fail", "--silent", "--insecure", "--output", "/dev/null", "https://127.0.0.1/healthz"]
