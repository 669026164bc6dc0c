"""Files and threads: the bottom layer of bake/ (it imports only errors.py).

    exrio          OpenEXR reading and writing: the tables' parts, the back ends' RGBA textures
    files          atomic writes, file hashes, a folder's job.json stamp
    paths          where an output folder keeps an entry's model and tables
    progress       progress lines with time-left estimates
    threads        the baker's thread pool, on the cores other processes leave free
"""
