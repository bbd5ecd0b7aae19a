"""The scan in parts: local refits on detector windows around a few bubbles, slabs of a tall scan's rows."""
