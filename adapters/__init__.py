"""Adapters: read and write the pose files of ACE, Marepo, HLoc and friends; intrinsics; the HLoc step."""
