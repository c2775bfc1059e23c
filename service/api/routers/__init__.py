"""One router per resource; service/api/app.py assembles them."""
