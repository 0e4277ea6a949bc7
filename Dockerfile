# One image for the API and the workers (docker-compose.yml picks the command).
FROM python:3.11-slim

ENV PYTHONDONTWRITEBYTECODE=1 \
    PYTHONUNBUFFERED=1 \
    PIP_NO_CACHE_DIR=1 \
    NUMBA_CACHE_DIR=/tmp/numba-cache

WORKDIR /app
COPY pyproject.toml README.md ./
COPY fpm fpm
COPY fpmcal fpmcal
COPY store store
COPY worker worker
COPY service service
COPY stack stack
COPY client client
COPY examples examples
RUN pip install -e . && useradd --create-home --uid 1000 fpm
USER fpm

EXPOSE 8000
CMD ["uvicorn", "service.main:app", "--host", "0.0.0.0", "--port", "8000"]
