"""``python -m service``: run the API with uvicorn on the embedded defaults
(127.0.0.1:8000)."""

from __future__ import annotations


def main() -> None:
    import uvicorn

    from .settings import get_settings

    s = get_settings()
    uvicorn.run("service.app:app", host=s.host, port=s.port)


if __name__ == "__main__":
    main()
