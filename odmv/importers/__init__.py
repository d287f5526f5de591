"""A user's data read in: import formats, one entry each (formats), the dataset a conversion
writes (convert), and captures as predict reads them (captures)."""
