# Load balancer for the scale-out profile: Debian's nginx in front of N ifnet-serve replicas.
# Built from the same base as the service image (context: docker/).
ARG BASE_IMAGE=debian:bookworm-slim
FROM ${BASE_IMAGE}

ENV DEBIAN_FRONTEND=noninteractive
RUN apt-get update \
 && apt-get install -y --no-install-recommends nginx \
 && rm -rf /var/lib/apt/lists/* /var/cache/apt/*.bin /etc/nginx/sites-enabled/* \
 && nginx -v

COPY nginx.conf /etc/nginx/ifnet.conf

# nginx runs unprivileged: it listens on 8080 and keeps its pid and temp files in /tmp.
USER www-data
EXPOSE 8080
HEALTHCHECK --interval=10s --timeout=5s --start-period=10s --retries=3 \
    CMD ["bash", "-c", "exec 3<>/dev/tcp/127.0.0.1/8080 && printf 'GET /lb-health HTTP/1.0\\r\\n\\r\\n' >&3 && head -n1 <&3 | grep -q ' 200 '"]
STOPSIGNAL SIGQUIT
CMD ["nginx", "-c", "/etc/nginx/ifnet.conf", "-e", "stderr"]
