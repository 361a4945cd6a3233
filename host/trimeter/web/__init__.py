"""`trimeter serve --http`: the instrument's web API, event websocket and page (see trimeter.web.app)."""
