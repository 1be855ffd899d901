# EvoColony: one image for `colony server`, `colony worker` and `colony agent`
# (docker-compose.yml). Credentials never enter it: .dockerignore keeps lab/ and .env out,
# and compose passes each service its env file and mounts what it must read.
FROM python:3.12-slim
WORKDIR /app
ENV PYTHONDONTWRITEBYTECODE=1 PYTHONUNBUFFERED=1 NUMBA_CACHE_DIR=/tmp/numba-cache
COPY . .
# uid 1000: compose runs the server as the owner of lab/ (COLONY_UID, default 1000);
# /data is where named volumes (the robots' state) are mounted, owned by this user
RUN pip install --no-cache-dir . && useradd --create-home --uid 1000 colony && mkdir -p /data \
    && chown colony /data
USER colony
EXPOSE 8000 7447
CMD ["colony", "--help"]
