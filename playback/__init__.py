"""haptex player: streams a tactile asset to a vibrotactile array (numpy, h5py, pyusb only)."""
