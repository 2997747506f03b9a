from facepipe.cli import main

if __name__ == "__main__":  # (a spawned child imports this module under another name)
    main()
