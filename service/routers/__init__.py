"""One router per resource; service/app.py assembles them."""
