# narxwatch service image: the REST API (`narxwatch serve`), job workers (`narxwatch worker`), migrations (`narxwatch db upgrade`)
# and the simulator client (`narxwatch-sim`). Used by docker-compose.yml.
FROM python:3.11-slim

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    PIP_DISABLE_PIP_VERSION_CHECK=1

WORKDIR /app

# The whole project (see .dockerignore): the package, alembic.ini and migrations/.
COPY . .

# psycopg[binary] bundles libpq, so the slim image needs no system packages for PostgreSQL.
RUN pip install . "psycopg[binary]>=3.2"

# Run unprivileged; var/ is the only place the service may write: the default SQLite file lives in
# the XDG data directory, $XDG_DATA_HOME/narxwatch/narxwatch.db.
ENV XDG_DATA_HOME=/app/var
RUN useradd --system --uid 10001 --user-group --home-dir /app --shell /usr/sbin/nologin narxwatch \
    && mkdir -p /app/var/keys /app/var/sealing \
    && chown -R narxwatch:narxwatch /app/var
USER narxwatch

EXPOSE 8000
CMD ["narxwatch", "serve", "--host", "0.0.0.0"]
