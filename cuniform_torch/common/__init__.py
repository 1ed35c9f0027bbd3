"""Low-level pieces every part of the library shares: argument checks, string options, tensor and device checks, atomic file writing, SE(2) frames."""
