# EvoColony: one image for `colony server` and `colony worker` (docker-compose.yml).
FROM python:3.12-slim
WORKDIR /app
ENV PYTHONDONTWRITEBYTECODE=1 PYTHONUNBUFFERED=1 NUMBA_CACHE_DIR=/tmp/numba-cache
COPY . .
RUN pip install --no-cache-dir . && useradd --create-home colony && mkdir -p /data \
    && chown colony /data
USER colony
EXPOSE 8000 7447
CMD ["colony", "--help"]
