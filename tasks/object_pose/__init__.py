"""The object's pose: register_object, estimate_adjustment, register_scan and their helpers."""
