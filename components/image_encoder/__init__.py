"""components::ImageEncoder: camera images compressed in the container (JPEG/PNG stills, H.264/H.265/AV1 video)."""
