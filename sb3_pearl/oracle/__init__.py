from sb3_pearl.oracle.oracle import Oracle

__all__ = ["Oracle"]
