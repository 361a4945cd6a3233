"""The file formats, between the model and the methods that use them: the appearance map (`.tmap`), the
in-scattering table (`.tins`), the device table (`.tlut`, a pure byte format with its reader and writer),
the container and schema they share, and the map pipeline's stages (which file each stage writes, and the
command that rebuilds it). Building these files is trimeter.maps'; reading a table from an instrument is
trimeter.device's."""
