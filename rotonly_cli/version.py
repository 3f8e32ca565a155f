"""rotonly's version, in a leaf of its own: the package's face (__init__) imports the API lazily,
so a module the API reaches that took the version from there would close an import cycle."""

__version__ = "0.1.0"
