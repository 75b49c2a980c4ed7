"""Pictures and Rerun recordings of maps, scenes, denoising and training; their layouts; live viewers; headless
screenshots."""
