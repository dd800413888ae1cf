"""Reactive control: the NEO-style QP twist controller and its collision safety filter (NeoSS)."""
